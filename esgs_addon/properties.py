"""The add-on's settings namespace: ``bpy.types.Scene.esgs``.

Each feature adds its own PropertyGroup as a pointer on the root group by calling
:func:`settings_group` from a module named ``esgs_addon/settings_<feature>.py``::

    @settings_group("colmap_import")
    class ESGS_PG_colmap_import(bpy.types.PropertyGroup): ...

and then reads ``context.scene.esgs.colmap_import``. The root group is built at
register time from what the feature modules declared.

A group's options are derived from a settings dataclass with :func:`property_annotations`
(names, defaults and help texts from the fields, one place for each option) and read back
with :func:`dataclass_from_properties`.
"""
from __future__ import annotations

import dataclasses
import importlib
import pkgutil
import typing
from collections.abc import Iterable
from typing import Any

import bpy

ORDER = 0  # register before any operator or panel

_GROUPS: dict[str, type] = {}


def settings_group(name: str):
    """Class decorator: expose the PropertyGroup as ``scene.esgs.<name>``."""

    def decorate(cls: type) -> type:
        _GROUPS[name] = cls
        return cls

    return decorate


_MAKERS = {bool: bpy.props.BoolProperty, int: bpy.props.IntProperty, float: bpy.props.FloatProperty,
           str: bpy.props.StringProperty}


def property_annotations(cls: type, extra: dict[str, dict] | None = None,
                         names: Iterable[str] | None = None) -> dict[str, Any]:
    """bpy property definitions for the bool/int/float/str fields of dataclass ``cls``.

    Each property takes its default from the field and its description from the field's
    ``metadata["help"]``; a str field with ``metadata["choices"]`` becomes an EnumProperty of
    those choices. Fields of other types (paths, tuples, nested settings) are left out.

    Args:
        cls: the settings dataclass.
        extra: per field, more keyword arguments of the property (``min``, ``subtype``, a
            ``name`` in place of the one made from the field name, ``search`` ...).
        names: only these fields (default: every field of a supported type).
    """
    extra = extra or {}
    hints = typing.get_type_hints(cls)
    wanted = None if names is None else set(names)
    annotations: dict[str, Any] = {}
    for fld in dataclasses.fields(cls):
        if wanted is not None and fld.name not in wanted:
            continue
        maker = _MAKERS.get(hints[fld.name])
        if maker is None:
            continue
        description = fld.metadata.get("help", "")
        options = {"name": fld.name.replace("_", " ").capitalize(), "description": description,
                   "default": fld.default, **extra.get(fld.name, {})}
        choices = fld.metadata.get("choices")
        if choices and hints[fld.name] is str:
            if not all(choices):
                # Blender accepts an item with an empty identifier, then warns on every read and
                # cannot select it again: name the choice instead (e.g. "preset" for "keep it")
                raise TypeError(f"{cls.__name__}.{fld.name} has an empty choice; give it a name")
            maker = bpy.props.EnumProperty
            options["items"] = [(str(choice), str(choice), description) for choice in choices]
        annotations[fld.name] = maker(**options)
    if wanted is not None and wanted - set(annotations):
        raise TypeError(f"{cls.__name__} has no bool/int/float/str fields {sorted(wanted - set(annotations))}")
    return annotations


def property_values(group: bpy.types.PropertyGroup, cls: type) -> dict[str, Any]:
    """The values of ``group``'s properties derived from ``cls`` (:func:`property_annotations`),
    by field name; fields the group lacks are left out (the dataclass keeps their defaults)."""
    values = {fld.name: getattr(group, fld.name) for fld in dataclasses.fields(cls) if hasattr(group, fld.name)}
    # Blender stores floats in single precision: 0.15 reads back as 0.15000000596. Seven
    # significant digits give back the decimal that was set (a default, a typed value), so
    # a run configured in Blender gets the same numbers as one configured from the CLI.
    return {name: float(f"{value:.7g}") if isinstance(value, float) else value for name, value in values.items()}


def dataclass_from_properties(group: bpy.types.PropertyGroup, cls: type) -> Any:
    """The ``cls`` settings held by ``group`` (see :func:`property_values`)."""
    return cls(**property_values(group, cls))


def _load_feature_settings() -> None:
    from . import __name__ as package_name
    from . import __path__ as package_path

    for info in pkgutil.iter_modules(package_path):
        if info.name.startswith("settings_"):
            importlib.import_module(f"{package_name}.{info.name}")


class ESGS_PG_root(bpy.types.PropertyGroup):
    """Root of every ESGS setting stored in a .blend (``scene.esgs``)."""


def register_hooks() -> None:
    _load_feature_settings()
    for name, cls in sorted(_GROUPS.items()):
        if not getattr(cls, "is_registered", False):
            bpy.utils.register_class(cls)
        ESGS_PG_root.__annotations__[name] = bpy.props.PointerProperty(type=cls)
    bpy.utils.register_class(ESGS_PG_root)
    bpy.types.Scene.esgs = bpy.props.PointerProperty(type=ESGS_PG_root)


def unregister_hooks() -> None:
    if hasattr(bpy.types.Scene, "esgs"):
        del bpy.types.Scene.esgs
    if ESGS_PG_root.is_registered:
        bpy.utils.unregister_class(ESGS_PG_root)
    for cls in reversed([c for _, c in sorted(_GROUPS.items())]):
        if getattr(cls, "is_registered", False):
            bpy.utils.unregister_class(cls)
