"""Blender-side glue: settings, preferences, job runner and bpy <-> core adapters.

Settings live in one namespace, ``bpy.types.Scene.esgs`` (see :mod:`.properties`).
"""
from __future__ import annotations


def register() -> None:
    from . import _registry
    import sys

    _registry.register_package(sys.modules[__name__])


def unregister() -> None:
    from . import _registry
    import sys

    _registry.unregister_package(sys.modules[__name__])
