"""Sidebar > ESGS > Synthetic Mars scene: generator settings and the Generate / Render buttons."""
from __future__ import annotations

import bpy

from ._section import ESGSSection, prop_column


class ESGS_PT_terrain(ESGSSection, bpy.types.Panel):
    """Generate a synthetic Mars scene and render it to a scene folder with ground truth."""

    bl_label = "Synthetic Mars Scene"
    bl_idname = "ESGS_PT_terrain"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        settings = context.scene.esgs.terrain
        column = prop_column(layout, settings, ("preset", "palette", "config", "seed", "views"))
        row = column.row(align=True)
        row.prop(settings, "width")
        row.prop(settings, "height")
        column.prop(settings, "samples")
        column.label(text="0 keeps the preset's value", icon="INFO")
        layout.operator("esgs.generate_terrain", icon="WORLD")
        prop_column(layout, settings, ("output_dir", "points_per_view", "sfm", "overwrite"))
        layout.operator("esgs.render_dataset", icon="RENDER_STILL")


CLASSES = (ESGS_PT_terrain,)
