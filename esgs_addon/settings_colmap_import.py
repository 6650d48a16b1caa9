"""Settings of the COLMAP import, read as ``scene.esgs.colmap_import``.

The properties are derived from :class:`~.colmap_scene.ColmapImportOptions` so each option
(name, default, help text) exists in one place.
"""
from __future__ import annotations

import bpy

from .colmap_scene import ColmapImportOptions
from .properties import dataclass_from_properties, property_annotations, settings_group

# a few options read better with a unit or a path widget in the UI
_EXTRA = {
    "point_radius": {"min": 0.0, "subtype": "DISTANCE", "precision": 4},
    "image_plane_distance": {"min": 1e-6, "subtype": "DISTANCE"},
    "undistorted_path": {"subtype": "DIR_PATH"},
}


def options_from_properties(group: bpy.types.PropertyGroup, cls: type = ColmapImportOptions):
    """Build the options dataclass from a property group derived by :func:`property_annotations`."""
    return dataclass_from_properties(group, cls)


@settings_group("colmap_import")
class ESGS_PG_colmap_import(bpy.types.PropertyGroup):
    """COLMAP import options (see ColmapImportOptions)."""

    __annotations__ = property_annotations(ColmapImportOptions, _EXTRA)
