"""Sidebar > ESGS > Labels: depth/normal labels of a COLMAP scene rendered from a mesh."""
from __future__ import annotations

import bpy

from ._section import ESGSSection

ORDER = 115  # after the import and training panels, before the results


class ESGS_PT_labels(ESGSSection, bpy.types.Panel):
    """Render depth/normal labels (priors/labels/) from a mesh or one rebuilt from the images."""

    bl_label = "Labels"
    bl_idname = "ESGS_PT_labels"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        settings = context.scene.esgs.labels
        column = layout.column()
        column.prop(settings, "scene_dir")
        column.prop(settings, "reconstruct")
        row = column.row()
        row.active = not settings.reconstruct
        row.prop(settings, "mesh_path")
        layout.operator("esgs.render_labels", icon="RENDER_STILL")


CLASSES = (ESGS_PT_labels,)
