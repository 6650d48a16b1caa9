"""Scene configs: presets, validation messages, serialisation round trips."""
from __future__ import annotations

import dataclasses
import json

import pytest

from esgs.core.errors import ConfigError
from esgs.core.terrain import (
    CAMERA_PRESETS, RenderConfig, RigConfig, SceneConfig, TerrainConfig, camera_preset, config_to_dict,
    list_presets, load_preset, load_scene_config, save_scene_config, scene_config_from_dict,
)

REQUIRED_PRESETS = ("cratered_plain", "rocky_slope", "dune_field", "layered_outcrop")


def test_required_presets_exist_and_validate():
    names = list_presets()
    for name in REQUIRED_PRESETS:
        assert name in names
    for name in names:
        config = load_preset(name)
        assert config.name == name
        assert config.description
        config.validate()


def test_some_preset_shows_sky_and_navcam_is_used():
    configs = [load_preset(name) for name in list_presets()]
    assert any(config.sky for config in configs)
    assert any(config.render.camera == "navcam" for config in configs)


def test_navcam_preset_matches_msl_navcam():
    navcam = camera_preset("navcam")
    assert (navcam.width, navcam.height, navcam.fov_deg, navcam.grayscale) == (1024, 1024, 45.0, True)
    assert navcam.vertical_fov_deg == pytest.approx(45.0)
    # 36 mm sensor, 45 deg: f = 18 / tan(22.5 deg)
    assert navcam.focal_mm == pytest.approx(18.0 / 0.41421356, rel=1e-6)
    assert camera_preset("generic_rgb").grayscale is False


def test_load_preset_overrides():
    config = load_preset("cratered_plain", seed=7, views=12, resolution=(480, 270), samples=8)
    assert config.seed == 7
    assert config.rig.views == 12
    assert (config.render.width, config.render.height, config.render.samples) == (480, 270, 8)
    # The rest of the preset is kept.
    assert config.terrain.crater_count == load_preset("cratered_plain").terrain.crater_count


def test_camera_override_replaces_preset_camera():
    config = load_preset("cratered_plain", camera="navcam", resolution=(256, 256))
    assert config.render.camera == "navcam"
    assert config.render.grayscale is True
    assert config.render.fov_deg == 45.0
    assert (config.render.width, config.render.height) == (256, 256)


@pytest.mark.parametrize("name", REQUIRED_PRESETS + ("rover_horizon",))
def test_json_round_trip_is_exact(tmp_path, name):
    config = load_preset(name, seed=3)
    path = tmp_path / "scene.json"
    save_scene_config(config, path)
    data = json.loads(path.read_text())
    assert data["seed"] == 3 and data["terrain"]["extent_m"] == config.terrain.extent_m
    assert load_scene_config(path) == config
    assert scene_config_from_dict(config_to_dict(config)) == config


def test_toml_scene_file(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('name = "mine"\nseed = 5\n[terrain]\nresolution = 129\ncrater_count = 4\n'
                    '[rig]\nkind = "aerial_nadir"\nviews = 4\nheight_m = 30.0\nradius_m = 10.0\n'
                    '[render]\ncamera = "navcam"\nwidth = 512\n')
    config = load_scene_config(path)
    assert (config.name, config.seed, config.terrain.resolution, config.rig.kind) == ("mine", 5, 129, "aerial_nadir")
    # camera preset fills what the table leaves out; explicit keys win.
    assert (config.render.width, config.render.height, config.render.grayscale) == (512, 1024, True)


def test_unknown_preset_names_the_available_ones():
    with pytest.raises(ConfigError, match="unknown scene preset 'moon'.*cratered_plain"):
        load_preset("moon")
    with pytest.raises(ConfigError, match="plain name"):
        load_preset("../secret")


@pytest.mark.parametrize("overrides, field_name", [
    ({"views": 0}, "rig.views"),
    ({"views": -3}, "rig.views"),
    ({"resolution": (-480, 270)}, "render.width"),
    ({"resolution": (480, 0)}, "render.height"),
    ({"samples": 0}, "render.samples"),
    ({"seed": -1}, "seed"),
    ({"camera": "hazcam"}, "render.camera"),
])
def test_bad_overrides_name_the_field(overrides, field_name):
    with pytest.raises(ConfigError) as info:
        load_preset("cratered_plain", **overrides)
    assert field_name in str(info.value)


@pytest.mark.parametrize("changes, field_name", [
    ({"resolution": 8}, "terrain.resolution"),
    ({"extent_m": -5.0}, "terrain.extent_m"),
    ({"extent_m": 0.0}, "terrain.extent_m"),
    ({"crater_count": -1}, "terrain.crater_count"),
    ({"crater_min_diameter_m": 5.0, "crater_max_diameter_m": 4.0}, "terrain.crater_max_diameter_m"),
    ({"crater_sfd_exponent": 0.0}, "terrain.crater_sfd_exponent"),
    ({"sand_fraction": 1.5}, "terrain.sand_fraction"),
    ({"rock_abundance": -0.1}, "terrain.rock_abundance"),
    ({"rock_abundance": 0.3, "rock_min_diameter_m": 0.02}, "terrain.rock_min_diameter_m"),
    ({"dune_asymmetry": 0.2}, "terrain.dune_asymmetry"),
    ({"ripple_amplitude_m": 0.05, "ripple_wavelength_m": 0.1}, "terrain.ripple_wavelength_m"),
    ({"resolution": 257.5}, "terrain.resolution"),
    ({"extent_m": float("nan")}, "terrain.extent_m"),
    ({"relief_octaves": True}, "terrain.relief_octaves"),
])
def test_terrain_validation_names_the_field(changes, field_name):
    config = dataclasses.replace(TerrainConfig(), **changes)
    with pytest.raises(ConfigError) as info:
        config.validate()
    assert field_name in str(info.value)


@pytest.mark.parametrize("changes, field_name", [
    ({"kind": "helicopter"}, "rig.kind"),
    ({"views": 0}, "rig.views"),
    ({"height_m": -2.0}, "rig.height_m"),
    ({"kind": "aerial_oblique", "pitch_deg": 0.0}, "rig.pitch_deg"),
    ({"sweep_deg": 0.0}, "rig.sweep_deg"),
])
def test_rig_validation_names_the_field(changes, field_name):
    with pytest.raises(ConfigError) as info:
        dataclasses.replace(RigConfig(), **changes).validate()
    assert field_name in str(info.value)


def test_render_validation_names_the_field():
    with pytest.raises(ConfigError, match="render.far_m"):
        RenderConfig(near_m=5.0, far_m=1.0).validate()
    with pytest.raises(ConfigError, match="render.fov_deg"):
        RenderConfig(fov_deg=0.0).validate()


def test_unknown_keys_are_rejected(tmp_path):
    path = tmp_path / "typo.toml"
    path.write_text("[terrain]\ncrater_cnt = 10\n")
    with pytest.raises(ConfigError, match="crater_cnt"):
        load_scene_config(path)
    path.write_text("[terrain\n")
    with pytest.raises(ConfigError, match="TOML"):
        load_scene_config(path)


def test_no_sky_scene_that_would_see_the_horizon_is_refused():
    config = load_preset("cratered_plain")
    config.rig.pitch_deg = -5.0
    with pytest.raises(ConfigError, match="sky is false.*rig.pitch_deg=-5.0"):
        config.validate()
    config.sky = True
    config.validate()


def test_sun_direction_follows_azimuth_convention():
    config = SceneConfig(sun_elevation_deg=90.0)
    assert config.sun_direction() == pytest.approx((0.0, 0.0, 1.0), abs=1e-12)
    config = SceneConfig(sun_elevation_deg=45.0, sun_azimuth_deg=90.0)
    assert config.sun_direction() == pytest.approx((0.0, 2 ** -0.5, 2 ** -0.5), abs=1e-12)


def test_camera_presets_table_is_complete():
    for name, values in CAMERA_PRESETS.items():
        assert camera_preset(name).camera == name
        for key, value in values.items():
            assert getattr(camera_preset(name), key) == value


def test_docs_cover_every_setting_and_preset():
    from pathlib import Path
    docs = (Path(__file__).resolve().parents[3] / "docs" / "terrain.md").read_text(encoding="utf-8")
    for cls in (SceneConfig, TerrainConfig, RigConfig, RenderConfig):
        for fld in dataclasses.fields(cls):
            assert f"`{fld.name}`" in docs, f"docs/terrain.md does not mention {cls.__name__}.{fld.name}"
    for name in list_presets():
        assert f"`{name}`" in docs, f"docs/terrain.md does not mention preset {name}"


def test_default_scene_config_is_valid():
    SceneConfig().validate()
