"""Sidebar > ESGS > Labels: depth/normal labels of a COLMAP scene rendered from a mesh."""
from __future__ import annotations

import bpy

from ._section import ESGSSection, dependent_prop, prop_column

ORDER = 115  # after the import and training panels, before the results


class ESGS_PT_labels(ESGSSection, bpy.types.Panel):
    """Render depth/normal labels (priors/labels/) from a mesh or one rebuilt from the images."""

    bl_label = "Labels"
    bl_idname = "ESGS_PT_labels"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context: bpy.types.Context) -> None:
        settings = context.scene.esgs.labels
        column = prop_column(self.layout, settings, ("scene_dir", "reconstruct"))
        dependent_prop(column, settings, "mesh_path", active=not settings.reconstruct)
        self.layout.operator("esgs.render_labels", icon="RENDER_STILL")


CLASSES = (ESGS_PT_labels,)
