"""Prior-map settings and the live state of the scene's priors job: ``scene.esgs.priors``."""
from __future__ import annotations

import bpy

from .properties import settings_group


@settings_group("priors")
class ESGS_PG_priors(bpy.types.PropertyGroup):
    """Options of ``esgs.compute_priors`` (a subset of ``esgs priors``) and the job's last known state.

    The scene folder is the training's (``scene.esgs.training``): priors are computed for the
    folder that will be trained on.
    """

    method: bpy.props.EnumProperty(
        name="Prior method", description="How to compute the prior maps written to SCENE/priors/<method>",
        items=(("auto", "Auto", "Auto: best of stereo labels, NDN and SfM per pixel, with a confidence map; "
                                "computes the sources it lacks first (stereo labels take minutes) and reuses "
                                "them while the images hold"),
               ("ndn", "NDN", "Dense relative depth from the NDN diffusion network and normals from the "
                              "completion network, both shipped (about 2 s per view on a CPU)"),
               ("sfm", "SfM", "Sparse depth at the COLMAP points each view observes (seconds)")),
        default="auto")
    ndn_weights: bpy.props.StringProperty(
        name="NDN weights", subtype="FILE_PATH",
        description="NDN weights file or model folder; named weights write depth and normals alone (empty: "
                    "$ESGS_NDN_WEIGHTS, else the two networks shipped with the extension)")

    # live state, written by the job poller
    status: bpy.props.StringProperty(name="Status", default="")
    step: bpy.props.IntProperty(name="Step", default=0)
    total: bpy.props.IntProperty(name="Total", default=0)
    progress: bpy.props.FloatProperty(name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR")
    error: bpy.props.StringProperty(name="Error", default="")
    last_scene_dir: bpy.props.StringProperty(name="Last scene", subtype="DIR_PATH", default="")
    last_method: bpy.props.StringProperty(name="Last method", default="")
