"""Settings of the COLMAP import, read as ``scene.esgs.colmap_import``.

The properties are derived from :class:`~.colmap_scene.ColmapImportOptions` so each option
(name, default, help text) exists in one place.
"""
from __future__ import annotations

import dataclasses
import typing

import bpy

from .colmap_scene import ColmapImportOptions
from .properties import settings_group

# a few options read better with a unit or a path widget in the UI
_EXTRA = {
    "point_radius": {"min": 0.0, "subtype": "DISTANCE", "precision": 4},
    "image_plane_distance": {"min": 1e-6, "subtype": "DISTANCE"},
    "undistorted_path": {"subtype": "DIR_PATH"},
}


def property_annotations(cls: type, extra: dict[str, dict] | None = None) -> dict[str, typing.Any]:
    """bpy property definitions for the bool/int/float/str fields of dataclass ``cls``."""
    extra = extra or {}
    hints = typing.get_type_hints(cls)
    makers = {bool: bpy.props.BoolProperty, int: bpy.props.IntProperty, float: bpy.props.FloatProperty,
              str: bpy.props.StringProperty}
    annotations = {}
    for fld in dataclasses.fields(cls):
        maker = makers.get(hints[fld.name])
        if maker is None:
            continue
        label = fld.name.replace("_", " ").capitalize()
        annotations[fld.name] = maker(
            name=label, description=fld.metadata.get("help", ""), default=fld.default, **extra.get(fld.name, {})
        )
    return annotations


def options_from_properties(group: bpy.types.PropertyGroup, cls: type = ColmapImportOptions):
    """Build the options dataclass from a property group derived by :func:`property_annotations`."""
    return cls(**{fld.name: getattr(group, fld.name) for fld in dataclasses.fields(cls)})


@settings_group("colmap_import")
class ESGS_PG_colmap_import(bpy.types.PropertyGroup):
    """COLMAP import options (see ColmapImportOptions)."""

    __annotations__ = property_annotations(ColmapImportOptions, _EXTRA)
