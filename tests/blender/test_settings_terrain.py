"""The synthetic-scene settings (esgs_addon/settings_terrain.py): every drop-down item can be
chosen, and the palette chosen in the panel reaches the scene that is generated."""
from __future__ import annotations

from dataclasses import dataclass, field

import pytest

bpy = pytest.importorskip("bpy")

from esgs.core.terrain.scene_job import KEEP_PALETTE, SceneJob
from esgs.esgs_addon.properties import property_annotations
from esgs.esgs_addon.settings_terrain import job_from_properties


def test_every_enum_item_has_an_identifier_and_the_default_is_one():
    for prop in bpy.context.scene.esgs.terrain.bl_rna.properties:
        if prop.type == "ENUM":
            # (the preset drop-down's items are made on drawing, from the preset names)
            assert all(item.identifier for item in prop.enum_items), prop.identifier
    palette = bpy.context.scene.esgs.terrain.bl_rna.properties["palette"]
    assert [item.identifier for item in palette.enum_items] == [KEEP_PALETTE, "mars", "varied"]
    assert palette.default == KEEP_PALETTE == SceneJob().palette


def test_the_chosen_palette_reaches_the_scene_config_and_can_be_set_back():
    settings = bpy.context.scene.esgs.terrain
    settings.preset, settings.seed = "rover_horizon", 3
    try:
        assert job_from_properties(settings).scene_config().palette == "mars"  # the preset's look
        settings.palette = "varied"
        assert job_from_properties(settings).scene_config().palette == "varied"
        settings.palette = KEEP_PALETTE
        assert job_from_properties(settings) == SceneJob(preset="rover_horizon", seed=3)
    finally:
        settings.property_unset("palette")
        settings.property_unset("preset")
        settings.property_unset("seed")


def test_a_choice_without_a_name_is_refused_when_the_properties_are_made():
    @dataclass
    class Options:
        look: str = field(default="", metadata={"help": "look", "choices": ("", "mars")})

    with pytest.raises(TypeError, match="Options.look has an empty choice"):
        property_annotations(Options)
