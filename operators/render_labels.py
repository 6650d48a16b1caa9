"""ESGS > Labels > Render Labels: a thin operator around ``render_labels`` (and ``reconstruct_mesh``)."""
from __future__ import annotations

import bpy

from ..core.errors import ConfigError
from ..core.formats.scene_dir import PriorSource, SceneDir
from ._blocking import BlockingJobOperator


class ESGS_OT_render_labels(BlockingJobOperator, bpy.types.Operator):
    """Render depth/normal labels of a COLMAP scene from a mesh with Cycles (CPU) into
    priors/labels/ (holes filled and flagged). Blocks until done"""

    bl_idname = "esgs.render_labels"
    bl_label = "Render Labels"
    bl_options = {"REGISTER"}

    scene_dir: bpy.props.StringProperty(name="Scene folder", subtype="DIR_PATH",
                                        description="Scene folder (empty = the Labels panel's)")
    mesh_path: bpy.props.StringProperty(name="Mesh", subtype="FILE_PATH",
                                        description="Mesh file (empty = the Labels panel's)")
    reconstruct: bpy.props.BoolProperty(name="Reconstruct mesh", default=False,
                                        description="Rebuild the mesh from the scene's images first")

    def run_job(self, context, progress):
        from pathlib import Path

        from ..esgs_addon.render_labels import render_labels

        settings = context.scene.esgs.labels
        scene_dir = bpy.path.abspath(self.scene_dir or settings.scene_dir)
        reconstruct = self.reconstruct or (not self.mesh_path and settings.reconstruct)
        mesh_path = bpy.path.abspath(self.mesh_path or settings.mesh_path)
        if not scene_dir:
            raise ConfigError("choose a scene folder first")
        if reconstruct:
            from ..core.labels.reconstruct import reconstruct_mesh

            reconstruction = reconstruct_mesh(Path(scene_dir), progress=progress)
            mesh_path, gaps_path = reconstruction["mesh"], reconstruction["gaps"]
        elif not mesh_path:
            raise ConfigError("choose a mesh file, or tick 'Reconstruct mesh'")
        else:
            gaps_path = None
        result = render_labels(scene_dir, mesh_path, method="reconstruct" if reconstruct else "mesh",
                               gaps_path=gaps_path, progress=progress)
        return f"Wrote labels of {len(result['views'])} views to {SceneDir(scene_dir).prior(PriorSource.LABELS)}"


CLASSES = (ESGS_OT_render_labels,)
