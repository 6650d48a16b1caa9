"""core/terrain/palette.py: scene palettes (sky colours, ground saturation), and how a scene job and the NDN
data builder choose them."""
from __future__ import annotations

import colorsys
import json

import pytest

from esgs.core.errors import ConfigError
from esgs.core.ndn.config import NDNDataConfig
from esgs.core.terrain.scene_job import SceneJob
from esgs.core.terrain.palette import MARS_PALETTE, ScenePalette, scene_palette, varied_palette


def test_mars_is_the_fixed_palette_and_varied_follows_the_seed():
    assert scene_palette("mars", 3) is MARS_PALETTE and scene_palette("mars", 4) is MARS_PALETTE
    assert scene_palette("varied", 3) == varied_palette(3)  # the same seed, the same sky
    assert len({varied_palette(seed) for seed in range(20)}) == 20
    with pytest.raises(ConfigError, match="unknown palette 'blue'"):
        scene_palette("blue", 0)


def test_varied_palettes_span_grey_to_dusty_and_are_valid():
    palettes = [varied_palette(seed) for seed in range(400)]
    for palette in palettes:
        palette.validate()
    saturation = [colorsys.rgb_to_hsv(*p.horizon)[1] for p in palettes]
    grey = sum(s == 0.0 for s in saturation) / len(palettes)
    assert 0.18 < grey < 0.32  # a quarter fully grey (Navcam's single band)
    assert max(saturation) > colorsys.rgb_to_hsv(*MARS_PALETTE.horizon)[1]  # and some dustier than the default
    brightness = [max(p.horizon) for p in palettes]
    assert min(brightness) < 0.5 < 0.9 < max(brightness)
    # the zenith darker than the horizon in some skies, brighter (towards the sun) in others
    assert any(max(p.zenith) < 0.5 * max(p.horizon) for p in palettes)
    assert any(max(p.zenith) > max(p.horizon) for p in palettes)
    surface = [p.surface_saturation for p in palettes]
    assert 0.25 < sum(s == 0.0 for s in surface) / len(palettes) < 0.42  # grey ground in about a third
    assert max(surface) > 1.0
    # drawn apart from the sky: grey ground under a coloured sky (the real mesh's rover views) occurs
    assert any(p.surface_saturation == 0.0 and colorsys.rgb_to_hsv(*p.horizon)[1] > 0.2 for p in palettes)
    assert MARS_PALETTE.surface_saturation == 1.0
    for palette in palettes:  # a grey sky sits over a grey plain
        if colorsys.rgb_to_hsv(*palette.horizon)[1] == 0.0:
            assert len(set(palette.distant_ground)) == 1 and len(set(palette.nadir)) == 1


def test_a_palette_with_a_colour_out_of_range_is_refused():
    with pytest.raises(ConfigError, match="colour zenith"):
        ScenePalette(nadir=(0, 0, 0), distant_ground=(0, 0, 0), horizon=(1, 1, 1), haze=(0.5, 0.5, 0.5),
                   zenith=(1.2, 0, 0)).validate()


def test_a_scene_job_sets_the_presets_palette():
    assert SceneJob(preset="rover_horizon", seed=3).scene_config().palette == "mars"
    config = SceneJob(preset="rover_horizon", seed=3, palette="varied").scene_config()
    assert config.palette == "varied" and config.seed == 3 and config.sky
    with pytest.raises(ConfigError, match="synthetic scenes only"):
        SceneJob(mesh="terrain.glb", palette="varied").validate()


def test_the_data_builder_checks_its_palette():
    NDNDataConfig(palette="varied").validate()
    with pytest.raises(ConfigError, match="palette must be one of mars, varied"):
        NDNDataConfig(palette="grey").validate()


def test_a_scene_job_keeps_a_config_files_palette_unless_told(tmp_path):
    from esgs.core.config import config_to_dict
    from esgs.core.terrain.presets import load_preset

    data = config_to_dict(load_preset("rover_horizon", seed=4))
    data["palette"] = "varied"
    saved = tmp_path / "scene.json"
    saved.write_text(json.dumps(data))
    assert SceneJob(config=str(saved)).scene_config().palette == "varied"
    assert SceneJob(config=str(saved), palette="mars").scene_config().palette == "mars"
    with pytest.raises(ConfigError, match="palette must be one of preset, mars, varied"):
        SceneJob(palette="").validate()
