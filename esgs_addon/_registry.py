"""Auto-discovery of Blender classes so each feature lives in its own module.

A module in ``esgs_addon/``, ``operators/`` or ``panels/`` takes part by defining
``CLASSES`` (a tuple of bpy classes, registered in order) and optionally
``register_hooks()`` / ``unregister_hooks()`` (menus, handlers). Modules whose name
starts with ``_`` are skipped.
"""
from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType
from typing import Callable


def feature_modules(package: ModuleType) -> list[ModuleType]:
    """The package's modules that define ``CLASSES``, sorted by ``ORDER`` then name."""
    modules = []
    for info in pkgutil.iter_modules(package.__path__):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{package.__name__}.{info.name}")
        if hasattr(module, "CLASSES") or hasattr(module, "register_hooks"):
            modules.append(module)
    return sorted(modules, key=lambda m: (getattr(m, "ORDER", 100), m.__name__))


def register_package(package: ModuleType) -> None:
    """Register every feature module's classes, then call its hooks."""
    import bpy

    for module in feature_modules(package):
        for cls in getattr(module, "CLASSES", ()):
            bpy.utils.register_class(cls)
        hook = getattr(module, "register_hooks", None)
        if hook:
            hook()


def unregister_package(package: ModuleType) -> None:
    """Undo :func:`register_package` in reverse order; tolerant of partial registration."""
    import bpy

    for module in reversed(feature_modules(package)):
        hook = getattr(module, "unregister_hooks", None)
        if hook:
            try:
                hook()
            except (ValueError, RuntimeError, AttributeError):
                pass
        for cls in reversed(getattr(module, "CLASSES", ())):
            if getattr(cls, "is_registered", False):
                bpy.utils.unregister_class(cls)


def file_load_hooks(handler: Callable[..., None]) -> tuple[Callable[[], None], Callable[[], None]]:
    """``(register_hooks, unregister_hooks)`` of a feature module whose ``handler`` (decorated
    with ``bpy.app.handlers.persistent``) runs after every file load: added to
    ``bpy.app.handlers.load_post`` once, removed again."""

    def register_hooks() -> None:
        import bpy

        if handler not in bpy.app.handlers.load_post:
            bpy.app.handlers.load_post.append(handler)

    def unregister_hooks() -> None:
        import bpy

        if handler in bpy.app.handlers.load_post:
            bpy.app.handlers.load_post.remove(handler)

    return register_hooks, unregister_hooks
