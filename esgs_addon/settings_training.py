"""Training settings and the live state of the scene's training job: ``scene.esgs.training``."""
from __future__ import annotations

import bpy

from .properties import settings_group


@settings_group("training")
class ESGS_PG_training(bpy.types.PropertyGroup):
    """Options of ``esgs.train`` (a subset of ``esgs train``) and the job's last known state."""

    scene_dir: bpy.props.StringProperty(
        name="Scene folder", subtype="DIR_PATH",
        description="COLMAP scene folder to train on (empty: the scene imported with ESGS > Import COLMAP)")
    run_dir: bpy.props.StringProperty(
        name="Run folder", subtype="DIR_PATH",
        description="Folder the run is written to (empty: a new folder in the preferences' runs folder)")
    iterations: bpy.props.IntProperty(
        name="Iterations", description="Training steps (the paper uses 30,000)", default=30_000, min=1)
    width: bpy.props.IntProperty(
        name="Image width", description="Train on images scaled to this width in pixels (0: full size)",
        default=0, min=0)
    # ESGS switches: shown and passed only when the installed trainer has them; off by
    # default like the trainer (a scene without priors/ trains as plain 3DGS)
    depth: bpy.props.BoolProperty(name="Depth prior", description="Align rendered depth with the depth priors",
                                  default=False)
    normal: bpy.props.BoolProperty(name="Normal prior", description="Align rendered normals with the normal priors",
                                   default=False)
    consistency: bpy.props.BoolProperty(
        name="Depth-normal consistency", description="Make rendered depth and normals agree (needs no prior)",
        default=False)
    gpdfn: bpy.props.BoolProperty(name="GPDFN", description="Neighbourhood fusion of Gaussian parameters",
                                  default=False)
    priors: bpy.props.StringProperty(
        name="Priors", description="priors/<source> to use: gt, labels, ndn or sfm (empty: none)", default="")
    import_result: bpy.props.BoolProperty(
        name="Import result", description="Import the trained Gaussians when training finishes", default=True)

    # live state, written by the job poller (also saved: the last run stays visible)
    status: bpy.props.StringProperty(name="Status", default="")
    stage: bpy.props.StringProperty(name="Stage", default="")
    step: bpy.props.IntProperty(name="Step", default=0)
    total: bpy.props.IntProperty(name="Total", default=0)
    progress: bpy.props.FloatProperty(name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR")
    loss: bpy.props.FloatProperty(name="Loss", default=-1.0)
    psnr: bpy.props.FloatProperty(name="PSNR", default=-1.0)
    n_gaussians: bpy.props.IntProperty(name="Gaussians", default=-1)
    eta_s: bpy.props.FloatProperty(name="ETA", default=-1.0)
    error: bpy.props.StringProperty(name="Error", default="")
    last_run_dir: bpy.props.StringProperty(name="Last run", subtype="DIR_PATH", default="")
    last_scene_dir: bpy.props.StringProperty(name="Last scene", subtype="DIR_PATH", default="")
