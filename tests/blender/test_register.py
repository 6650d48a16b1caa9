"""The add-on registers and unregisters cleanly, any number of times."""
from __future__ import annotations

import bpy

import esgs


def _esgs_classes() -> list[str]:
    return [name for name in dir(bpy.types) if name.startswith("ESGS_")]


def test_registered_by_fixture_exposes_settings_and_panel():
    assert hasattr(bpy.types.Scene, "esgs")
    assert "ESGS_PT_main" in _esgs_classes()
    assert bpy.context.scene.esgs is not None


def test_register_twice_is_harmless_and_unregister_removes_everything():
    esgs.register()  # already registered by the fixture
    esgs.unregister()
    assert not hasattr(bpy.types.Scene, "esgs")
    assert _esgs_classes() == []
    esgs.unregister()  # harmless when not registered
    esgs.register()
    assert hasattr(bpy.types.Scene, "esgs") and "ESGS_PT_main" in _esgs_classes()

