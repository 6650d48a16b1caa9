"""File > Import / File > Export entries of our operators.

A module that adds a menu entry writes::

    register_hooks, unregister_hooks = menu_hooks("TOPBAR_MT_file_import", ESGS_OT_import_colmap,
                                                  "COLMAP Scene (ESGS)")

and the registry (``esgs_addon/_registry.py``) calls the two hooks with the module's classes.
"""
from __future__ import annotations

from typing import Callable

import bpy


def menu_hooks(menu: str, operator: type, label: str) -> tuple[Callable[[], None], Callable[[], None]]:
    """``(register_hooks, unregister_hooks)`` adding and removing one entry of ``menu``.

    Args:
        menu: the menu's type name in ``bpy.types``, e.g. ``"TOPBAR_MT_file_import"`` (looked up
            when the hooks run, so importing the module needs no registered menu).
        operator: the operator class the entry runs (its ``bl_idname``); the entry's draw
            function is attributed to the operator's module, so the entry can be found by it.
        label: the entry's text.
    """
    idname = operator.bl_idname

    def menu_entry(self, context: bpy.types.Context) -> None:
        self.layout.operator(idname, text=label)

    menu_entry.__module__ = operator.__module__

    def register_hooks() -> None:
        getattr(bpy.types, menu).append(menu_entry)

    def unregister_hooks() -> None:
        getattr(bpy.types, menu).remove(menu_entry)

    return register_hooks, unregister_hooks
