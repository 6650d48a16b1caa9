"""Sidebar > ESGS > Synthetic Mars scene: generator settings and the Generate / Render buttons."""
from __future__ import annotations

import bpy

from ._section import ESGSSection


class ESGS_PT_terrain(ESGSSection, bpy.types.Panel):
    """Generate a synthetic Mars scene and render it to a scene folder with ground truth."""

    bl_label = "Synthetic Mars Scene"
    bl_idname = "ESGS_PT_terrain"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        settings = context.scene.esgs.terrain
        column = layout.column()
        column.prop(settings, "preset")
        column.prop(settings, "config")
        column.prop(settings, "seed")
        column.prop(settings, "views")
        row = column.row(align=True)
        row.prop(settings, "width")
        row.prop(settings, "height")
        column.prop(settings, "samples")
        column.label(text="0 keeps the preset's value", icon="INFO")
        layout.operator("esgs.generate_terrain", icon="WORLD")
        column = layout.column()
        column.prop(settings, "output_dir")
        column.prop(settings, "points_per_view")
        column.prop(settings, "sfm")
        column.prop(settings, "overwrite")
        layout.operator("esgs.render_dataset", icon="RENDER_STILL")


CLASSES = (ESGS_PT_terrain,)
