"""The add-on's settings namespace: ``bpy.types.Scene.esgs``.

Each feature adds its own PropertyGroup as a pointer on the root group by calling
:func:`settings_group` from a module named ``esgs_addon/settings_<feature>.py``::

    @settings_group("colmap_import")
    class ESGS_PG_colmap_import(bpy.types.PropertyGroup): ...

and then reads ``context.scene.esgs.colmap_import``. The root group is built at
register time from what the feature modules declared.
"""
from __future__ import annotations

import importlib
import pkgutil

import bpy

ORDER = 0  # register before any operator or panel

_GROUPS: dict[str, type] = {}


def settings_group(name: str):
    """Class decorator: expose the PropertyGroup as ``scene.esgs.<name>``."""

    def decorate(cls: type) -> type:
        _GROUPS[name] = cls
        return cls

    return decorate


def _load_feature_settings() -> None:
    from . import __path__ as package_path, __name__ as package_name

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
