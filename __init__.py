"""ESGS for Blender: the extension entry point and the ``esgs`` Python package.

Importing this package never imports ``bpy``; only :func:`register` does, so
``import esgs.core`` works in any Python that has the engine's dependencies.
"""
from __future__ import annotations

__version__ = "0.1.0"

_registered = False


def register() -> None:
    """Register every Blender class of the add-on. Calling it twice is harmless."""
    global _registered
    if _registered:
        return
    from . import esgs_addon, operators, panels

    # settings first, then the operators, then the panels that draw both
    esgs_addon.register()
    operators.register()
    panels.register()
    _registered = True


def unregister() -> None:
    """Remove everything :func:`register` added. Harmless when not registered."""
    global _registered
    if not _registered:
        return
    from . import esgs_addon, operators, panels

    panels.unregister()
    operators.unregister()
    esgs_addon.unregister()
    _registered = False
