"""Settings of the synthetic Mars scene generator, read as ``scene.esgs.terrain``.

The properties are derived from :class:`~esgs.core.terrain.scene_job.SceneJob` (the same
options as ``esgs scene``), plus the output folder; the preset is a drop-down of the
bundled presets.
"""
from __future__ import annotations

import dataclasses

import bpy

from ..core.terrain.scene_job import SceneJob
from .properties import property_annotations, settings_group

_EXTRA = {
    "seed": {"min": -1},
    "views": {"min": 0, "soft_max": 200},
    "width": {"min": 0, "soft_max": 4096, "subtype": "PIXEL"},
    "height": {"min": 0, "soft_max": 4096, "subtype": "PIXEL"},
    "samples": {"min": 0, "soft_max": 1024},
    "points_per_view": {"min": 1, "soft_max": 20000},
    "config": {"subtype": "FILE_PATH"},
}


def _preset_items(self, context):
    from ..core.terrain import list_presets

    # Blender keeps a reference to the strings of dynamic enum items: cache them
    items = [(name, name.replace("_", " ").capitalize(), f"scene preset {name}") for name in list_presets()]
    _preset_items.cache = items
    return items


def job_from_properties(group: bpy.types.PropertyGroup) -> SceneJob:
    """The SceneJob described by ``scene.esgs.terrain``."""
    return SceneJob(**{fld.name: getattr(group, fld.name) for fld in dataclasses.fields(SceneJob)})


_annotations = property_annotations(SceneJob, _EXTRA)
_annotations["preset"] = bpy.props.EnumProperty(name="Preset", description="scene preset", items=_preset_items)
_annotations["output_dir"] = bpy.props.StringProperty(
    name="Output folder", description="scene folder to write (must not exist unless Overwrite is on)", subtype="DIR_PATH")


@settings_group("terrain")
class ESGS_PG_terrain(bpy.types.PropertyGroup):
    """Synthetic Mars scene options (see SceneJob)."""

    __annotations__ = _annotations
