"""bpy-module tests: each test starts from Blender's factory settings with the add-on registered."""
from __future__ import annotations

import pytest

bpy = pytest.importorskip("bpy", reason="the bpy module is not installed")


@pytest.fixture(autouse=True)
def fresh_blender():
    import esgs

    bpy.ops.wm.read_factory_settings(use_empty=True)
    esgs.register()
    yield bpy
    esgs.unregister()
    bpy.ops.wm.read_factory_settings(use_empty=True)
