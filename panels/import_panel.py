"""Sidebar > ESGS > Import: COLMAP import settings and the import/export buttons."""
from __future__ import annotations

import bpy

from ._section import ESGSSection, dependent_prop, prop_column


class ESGS_PT_import(ESGSSection, bpy.types.Panel):
    """Bring COLMAP scenes in (and Blender cameras out)."""

    bl_label = "Import"
    bl_idname = "ESGS_PT_import"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        settings = context.scene.esgs.colmap_import
        column = prop_column(layout, settings, ("import_points",))
        dependent_prop(column, settings, "point_radius", active=settings.import_points)
        column.prop(settings, "image_planes")
        dependent_prop(column, settings, "image_plane_distance", active=settings.image_planes)
        for name in ("orient_up", "set_scene_resolution", "undistorted_path", "collection_name"):
            column.prop(settings, name)
        layout.operator("esgs.import_colmap", icon="IMPORT")
        layout.operator("esgs.export_colmap", icon="EXPORT")


CLASSES = (ESGS_PT_import,)
