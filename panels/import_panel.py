"""Sidebar > ESGS > Import: COLMAP import settings and the import/export buttons."""
from __future__ import annotations

import bpy

from ._section import ESGSSection


class ESGS_PT_import(ESGSSection, bpy.types.Panel):
    """Bring COLMAP scenes in (and Blender cameras out)."""

    bl_label = "Import"
    bl_idname = "ESGS_PT_import"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        settings = context.scene.esgs.colmap_import
        column = layout.column()
        column.prop(settings, "import_points")
        row = column.row()
        row.active = settings.import_points
        row.prop(settings, "point_radius")
        column.prop(settings, "image_planes")
        row = column.row()
        row.active = settings.image_planes
        row.prop(settings, "image_plane_distance")
        column.prop(settings, "orient_up")
        column.prop(settings, "set_scene_resolution")
        column.prop(settings, "undistorted_path")
        column.prop(settings, "collection_name")
        layout.operator("esgs.import_colmap", icon="IMPORT")
        layout.operator("esgs.export_colmap", icon="EXPORT")


CLASSES = (ESGS_PT_import,)
