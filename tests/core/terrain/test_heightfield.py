"""The terrain generator: determinism, grid convention, samplers, ray casting, sand."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from esgs.core.errors import ConfigError
from esgs.core.terrain import Terrain, TerrainConfig, generate_terrain, load_preset
from esgs.core.terrain.craters import apply_craters
from esgs.core.terrain.noise import fractal_noise


def small_config(**changes) -> TerrainConfig:
    base = dict(resolution=129, extent_m=40.0, relief_amplitude_m=0.5, relief_wavelength_m=15.0,
                crater_count=30, crater_min_diameter_m=1.0, crater_max_diameter_m=8.0,
                rock_abundance=0.05, rock_min_diameter_m=0.3, rock_max_diameter_m=1.5,
                sand_fraction=0.3, dune_amplitude_m=0.5, dune_wavelength_m=6.0)
    base.update(changes)
    return TerrainConfig(**base)


def test_same_seed_same_terrain_and_different_seed_differs():
    config = small_config()
    first, second = generate_terrain(config, seed=11), generate_terrain(config, seed=11)
    np.testing.assert_array_equal(first.heights, second.heights)
    np.testing.assert_array_equal(first.sand_mask, second.sand_mask)
    np.testing.assert_array_equal(first.craters, second.craters)
    np.testing.assert_array_equal(first.rocks, second.rocks)
    other = generate_terrain(config, seed=12)
    assert np.abs(other.heights - first.heights).mean() > 0.05
    assert not np.array_equal(other.craters[:, :2], first.craters[:, :2])
    assert not np.array_equal(other.rocks[:, :2], first.rocks[:, :2])


def test_output_types_and_shapes():
    config = small_config()
    terrain = generate_terrain(config, seed=1)
    assert terrain.heights.shape == (129, 129) and terrain.heights.dtype == np.float32
    assert terrain.sand_mask.shape == (129, 129) and terrain.sand_mask.dtype == np.float32
    assert terrain.sand_mask.min() >= 0 and terrain.sand_mask.max() <= 1
    assert terrain.craters.shape == (30, 5)
    assert terrain.rocks.ndim == 2 and terrain.rocks.shape[1] == 7 and len(terrain.rocks) > 10
    assert terrain.cell_m == pytest.approx(40.0 / 128)
    assert np.isfinite(terrain.heights).all()
    # The named components add up to the heightfield.
    total = sum(layer.astype(np.float64) for layer in terrain.components.values())
    np.testing.assert_allclose(total, terrain.heights, atol=1e-4)


def test_components_use_independent_random_streams():
    config = small_config()
    more_craters = dataclasses.replace(config, crater_count=60)
    a, b = generate_terrain(config, seed=5), generate_terrain(more_craters, seed=5)
    np.testing.assert_array_equal(a.components["relief"], b.components["relief"])


def test_grid_convention_x_along_columns_y_along_rows():
    # A pure regional slope rising toward +x (azimuth 0): h = tan(slope) * x.
    config = TerrainConfig(resolution=65, extent_m=64.0, relief_amplitude_m=0.0, slope_deg=10.0,
                           slope_azimuth_deg=0.0, sand_fraction=0.0)
    terrain = generate_terrain(config, seed=0)
    x, y = terrain.coordinates
    assert x[0] == -32.0 and x[-1] == 32.0 and x[32] == 0.0
    expected = math.tan(math.radians(10.0)) * x
    np.testing.assert_allclose(terrain.heights, np.broadcast_to(expected[None, :], (65, 65)), atol=1e-5)
    # Now rising toward +y (azimuth 90): rows vary, columns do not.
    north = generate_terrain(dataclasses.replace(config, slope_azimuth_deg=90.0), seed=0)
    np.testing.assert_allclose(north.heights, np.broadcast_to(expected[:, None], (65, 65)), atol=1e-5)


def test_height_and_normal_samplers_on_a_plane():
    resolution, extent = 33, 20.0
    axis = np.linspace(-extent / 2, extent / 2, resolution)
    a, b, c = 0.3, -0.2, 1.5
    heights = (a * axis[None, :] + b * axis[:, None] + c).astype(np.float32)
    terrain = Terrain(heights=heights, extent_m=extent, sand_mask=np.zeros_like(heights))
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-9.9, 9.9, 200), rng.uniform(-9.9, 9.9, 200)
    np.testing.assert_allclose(terrain.height_at(x, y), a * x + b * y + c, atol=1e-5)
    normals = terrain.normal_at(x, y)
    expected = np.array([-a, -b, 1.0]) / math.sqrt(a * a + b * b + 1)
    np.testing.assert_allclose(normals, np.broadcast_to(expected, normals.shape), atol=1e-6)
    # Exact at grid nodes, and scalars broadcast.
    assert terrain.height_at(axis[3], axis[7]) == pytest.approx(heights[7, 3])


def test_raycast_against_a_plane():
    resolution, extent = 65, 40.0
    axis = np.linspace(-extent / 2, extent / 2, resolution)
    heights = (0.1 * axis[None, :] + np.zeros((resolution, 1))).astype(np.float32)
    terrain = Terrain(heights=heights, extent_m=extent, sand_mask=np.zeros_like(heights))
    origins = np.array([[0.0, 0.0, 5.0], [-5.0, 3.0, 2.0], [0.0, 0.0, 5.0], [0.0, 0.0, 5.0]])
    directions = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, -0.5], [1.0, 0.0, 0.2], [0.0, 1.0, -0.01]])
    distances = terrain.raycast(origins, directions)
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    # Plane z = 0.1 x: origin + t d meets it where oz + t dz = 0.1 (ox + t dx).
    for index in range(2):
        o, d = origins[index], unit[index]
        t = (0.1 * o[0] - o[2]) / (d[2] - 0.1 * d[0])
        assert distances[index] == pytest.approx(t, abs=1e-3)
    assert math.isinf(distances[2])  # climbs away faster than the plane
    assert math.isinf(distances[3])  # leaves the square before reaching the ground


def test_single_crater_shape():
    resolution, extent = 257, 40.0
    heights = np.zeros((resolution, resolution))
    diameter, depth = 10.0, 2.0
    apply_craters(heights, np.array([[0.0, 0.0, diameter, depth, 0.0]]), extent, rim_ratio=0.04)
    terrain = Terrain(heights=heights.astype(np.float32), extent_m=extent, sand_mask=np.zeros_like(heights, dtype=np.float32))
    radii = np.linspace(0.0, 20.0, 401)
    profile = terrain.height_at(radii, np.zeros_like(radii))
    assert profile[0] == pytest.approx(-depth, abs=0.05)
    crest = radii[np.argmax(profile)]
    assert crest == pytest.approx(diameter / 2, abs=0.5)
    assert profile.max() == pytest.approx(0.04 * diameter, rel=0.25)
    # Ejecta thins outward and ends at three radii.
    assert profile[np.searchsorted(radii, 7.5)] > profile[np.searchsorted(radii, 10.0)] > 0
    assert np.abs(profile[radii >= 15.5]).max() < 1e-9
    # Radially symmetric: the same along y.
    np.testing.assert_allclose(terrain.height_at(np.zeros_like(radii), radii), profile, atol=1e-3)


def test_degraded_crater_is_shallower_with_a_lower_rim():
    def crater(degradation):
        heights = np.zeros((129, 129))
        depth = 0.2 * 8.0 * (1 - 0.8 * degradation)
        apply_craters(heights, np.array([[0.0, 0.0, 8.0, depth, degradation]]), 20.0, rim_ratio=0.04)
        return heights
    fresh, old = crater(0.0), crater(1.0)
    assert old.min() > 0.5 * fresh.min()
    assert old.max() < 0.5 * fresh.max()


def test_sand_fraction_is_followed():
    for fraction in (0.0, 0.25, 0.6, 1.0):
        terrain = generate_terrain(small_config(sand_fraction=fraction, rock_abundance=0.0), seed=2)
        assert terrain.sand_mask.mean() == pytest.approx(fraction, abs=0.06)


def test_sand_prefers_low_ground():
    config = small_config(sand_fraction=0.3, sand_low_bias=1.0, dune_amplitude_m=0.0, rock_abundance=0.0)
    terrain = generate_terrain(config, seed=4)
    from scipy import ndimage
    local = terrain.components["relief"] + terrain.components["craters"]
    local = local - ndimage.gaussian_filter(local, 40)
    sandy = terrain.sand_mask > 0.5
    assert local[sandy].mean() < local[~sandy].mean() - 0.1


def test_fractal_noise_statistics_and_octaves():
    axis = np.linspace(0.0, 100.0, 257)
    field = fractal_noise(axis, axis, np.random.default_rng(0), wavelength_m=25.0, octaves=5)
    assert field.mean() == pytest.approx(0.0, abs=1e-9) and field.std() == pytest.approx(1.0)
    # Rougher settings put more energy into short wavelengths (larger mean gradient).
    smooth = fractal_noise(axis, axis, np.random.default_rng(0), wavelength_m=25.0, octaves=5, roughness=0.3)
    rough = fractal_noise(axis, axis, np.random.default_rng(0), wavelength_m=25.0, octaves=5, roughness=0.8)
    assert np.abs(np.diff(rough, axis=1)).mean() > 1.5 * np.abs(np.diff(smooth, axis=1)).mean()


def test_layers_make_terraces():
    config = small_config(crater_count=0, relief_amplitude_m=0.0, slope_deg=20.0, layer_thickness_m=1.0,
                          layer_sharpness=1.0, sand_fraction=0.0, rock_abundance=0.0)
    terrain = generate_terrain(config, seed=0)
    steps = np.diff(terrain.heights[64].astype(np.float64))
    # Mostly flat treads with a few steep risers, unlike the constant slope underneath.
    assert np.median(steps) < 0.2 * steps.mean()
    assert steps.max() > 3 * steps.mean()


def test_bad_inputs_raise_config_error():
    with pytest.raises(ConfigError, match="terrain.extent_m"):
        generate_terrain(TerrainConfig(extent_m=-1.0))
    with pytest.raises(ConfigError, match="seed"):
        generate_terrain(TerrainConfig(resolution=33), seed=-4)


def test_progress_reports_reach_the_total():
    events = []
    generate_terrain(small_config(), seed=0, progress=events.append)
    assert events[-1].step == events[-1].total and all(event.stage == "terrain" for event in events)


@pytest.mark.slow
def test_every_preset_generates():
    from esgs.core.terrain import list_presets
    for name in list_presets():
        config = load_preset(name)
        terrain = generate_terrain(config.terrain, seed=config.seed)
        assert np.isfinite(terrain.heights).all()


def test_young_crater_erases_older_ones_inside_it():
    resolution, extent = 257, 40.0
    big = [0.0, 0.0, 16.0, 3.2, 0.0]       # fresh
    small = [2.0, 1.0, 3.0, 0.1, 1.0]      # degraded: older
    def stamp(*craters):
        heights = np.zeros((resolution, resolution))
        apply_craters(heights, np.array(craters), extent, rim_ratio=0.04)
        return heights
    alone, both = stamp(big), stamp(big, small)
    # The fresh crater formed later: the old small one inside its bowl is gone.
    # (Only a trace of its outer ejecta, beyond the fully replaced floor, remains.)
    assert np.abs(both - alone).max() < 0.01 * np.abs(stamp(small)).max()
    # Made younger than the big one, the small crater survives inside the bowl.
    young_small = [2.0, 1.0, 3.0, 0.6, 0.0]
    old_big = [0.0, 0.0, 16.0, 0.64, 1.0]
    survives = stamp(old_big, young_small) - stamp(old_big)
    assert survives.min() < -0.5


def test_crater_floor_keeps_the_regional_tilt():
    resolution, extent = 129, 40.0
    axis = np.linspace(-20, 20, resolution)
    tilt = 0.2 * axis[None, :] + np.zeros((resolution, 1))
    heights = tilt.copy()
    apply_craters(heights, np.array([[0.0, 0.0, 12.0, 2.4, 0.0]]), extent, rim_ratio=0.04)
    flat = np.zeros((resolution, resolution))
    apply_craters(flat, np.array([[0.0, 0.0, 12.0, 2.4, 0.0]]), extent, rim_ratio=0.04)
    # On a tilted plane the crater is the same shape, just riding on the tilt.
    np.testing.assert_allclose(heights - tilt, flat, atol=1e-6)


def test_save_and_load_terrain_round_trip(tmp_path):
    from esgs.core.errors import DatasetError, FormatError
    from esgs.core.terrain import load_terrain, save_terrain
    terrain = generate_terrain(small_config(), seed=6)
    path = tmp_path / "terrain.npz"
    save_terrain(terrain, path, include_components=True)
    loaded = load_terrain(path)
    for name in ("heights", "sand_mask", "craters", "rocks"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(terrain, name))
        assert getattr(loaded, name).dtype == getattr(terrain, name).dtype
    assert loaded.extent_m == terrain.extent_m
    assert set(loaded.components) == set(terrain.components)
    assert loaded.height_at(1.3, -2.2) == terrain.height_at(1.3, -2.2)
    assert [p.name for p in tmp_path.iterdir()] == ["terrain.npz"]  # no temporary left behind
    np.savez(tmp_path / "other.npz", heights=np.zeros((3, 3)))
    with pytest.raises(FormatError, match="missing"):
        load_terrain(tmp_path / "other.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError):
        load_terrain(tmp_path / "junk.npz")
    with pytest.raises(DatasetError, match="not found"):
        load_terrain(tmp_path / "absent.npz")


def test_raycast_from_outside_the_square_never_goes_backwards():
    resolution, extent = 33, 20.0
    heights = np.full((resolution, resolution), 3.0, dtype=np.float32)
    terrain = Terrain(heights=heights, extent_m=extent, sand_mask=np.zeros_like(heights))
    # Starts outside at x = -15, below the plateau's top: it meets the square's edge at x = -10.
    distance = terrain.raycast(np.array([[-15.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))[0]
    assert 5.0 <= distance <= 5.0 + 0.5 * terrain.cell_m + 1e-9
    # From above, outside, descending onto the plateau: an ordinary hit.
    distance = terrain.raycast(np.array([[-15.0, 0.0, 8.0]]), np.array([[1.0, 0.0, -0.5]]))[0]
    assert distance * 0.5 / math.sqrt(1.25) == pytest.approx(5.0, abs=1e-3)


def test_layers_only_show_on_slopes():
    gentle = small_config(crater_count=0, relief_amplitude_m=0.0, slope_deg=2.0, sand_fraction=0.0, rock_abundance=0.0)
    plain = generate_terrain(gentle, seed=0)
    layered = generate_terrain(dataclasses.replace(gentle, layer_thickness_m=0.3, layer_sharpness=1.0), seed=0)
    np.testing.assert_allclose(layered.heights, plain.heights, atol=1e-6)
