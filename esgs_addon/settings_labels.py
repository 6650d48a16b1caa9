"""Settings of the label rendering, read as ``scene.esgs.labels`` (the Labels panel)."""
from __future__ import annotations

import bpy

from .properties import settings_group


@settings_group("labels")
class ESGS_PG_labels(bpy.types.PropertyGroup):
    """Where the labels go and which mesh they come from (see esgs.render_labels)."""

    scene_dir: bpy.props.StringProperty(name="Scene folder", subtype="DIR_PATH",
                                        description="Scene folder holding images/ and sparse/0; labels go to priors/labels")
    mesh_path: bpy.props.StringProperty(name="Mesh", subtype="FILE_PATH",
                                        description="Mesh (.ply/.obj) in the cameras' frame and units")
    reconstruct: bpy.props.BoolProperty(
        name="Reconstruct mesh", default=False,
        description="Rebuild a mesh from the scene's own images and poses (CPU stereo, minutes) instead of a mesh file")
