"""Blender panels: one module per feature, discovered at register time (see esgs_addon/_registry.py)."""
from __future__ import annotations

import sys


def register() -> None:
    from ..esgs_addon import _registry

    _registry.register_package(sys.modules[__name__])


def unregister() -> None:
    from ..esgs_addon import _registry

    _registry.unregister_package(sys.modules[__name__])
