"""Rocks: Golombek-Rapp cumulative area fraction, placement on the ground."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.terrain import TerrainConfig, generate_terrain
from esgs.core.terrain.rocks import cumulative_area_fraction, expected_rock_count, rock_q, sample_rock_diameters


def test_q_of_k_matches_the_model():
    assert rock_q(0.1) == pytest.approx(1.79 + 1.52)
    assert cumulative_area_fraction(0.0, 0.2) == pytest.approx(0.2)
    assert cumulative_area_fraction(1.0, 0.2) == pytest.approx(0.2 * np.exp(-(1.79 + 0.76)))


@pytest.mark.parametrize("abundance", [0.03, 0.1, 0.25])
def test_covered_area_follows_golombek_rapp(abundance):
    low, high, area = 0.2, 3.0, 40000.0
    diameters = sample_rock_diameters(abundance, low, high, area, np.random.default_rng(2))
    assert diameters.min() >= low - 1e-12 and diameters.max() <= high + 1e-12
    checked = 0
    for diameter in (0.2, 0.3, 0.5, 0.8, 1.2):
        if expected_rock_count(abundance, diameter, high, area) < 40:
            continue  # too few rocks that large for a stable comparison
        checked += 1
        empirical = np.sum(np.pi / 4 * diameters[diameters >= diameter] ** 2) / area
        model = cumulative_area_fraction(diameter, abundance) - cumulative_area_fraction(high, abundance)
        assert empirical == pytest.approx(model, rel=0.1), diameter
    assert checked >= 3


def test_expected_count_matches_a_direct_integral():
    # n(D) = 4 k q exp(-qD) / (pi D^2); integrate with a fine midpoint rule.
    k, low, high = 0.08, 0.25, 2.0
    q = rock_q(k)
    edges = np.linspace(low, high, 200001)
    middle = 0.5 * (edges[1:] + edges[:-1])
    direct = np.sum(4 * k * q * np.exp(-q * middle) / (np.pi * middle ** 2)) * (high - low) / 200000
    assert expected_rock_count(k, low, high, 1.0) == pytest.approx(direct, rel=1e-3)
    assert expected_rock_count(0.0, low, high, 1.0) == 0.0


def test_rocks_sit_on_the_ground_and_avoid_sand():
    config = TerrainConfig(resolution=129, extent_m=60.0, relief_amplitude_m=0.5, relief_wavelength_m=30.0,
                           rock_abundance=0.1, rock_min_diameter_m=0.3, rock_max_diameter_m=2.0,
                           rock_embed_fraction=0.25, rock_sand_avoidance=1.0, sand_fraction=0.5,
                           sand_low_bias=0.0)
    terrain = generate_terrain(config, seed=3)
    x, y, z_base, diameter, height, yaw, shape_seed = terrain.rocks.T
    assert len(x) == round(expected_rock_count(0.1, 0.3, 2.0, 3600.0))
    assert np.abs(x).max() <= 30 and np.abs(y).max() <= 30
    ground = terrain.height_at(x, y)
    angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)[:, None]
    lowest = np.min(terrain.height_at(x + 0.5 * diameter * np.cos(angles), y + 0.5 * diameter * np.sin(angles)), axis=0)
    lowest = np.minimum(lowest, ground)
    # Partly buried: the bottom below the ground by at least the embedded share, yet not
    # deeper than that below the lowest ground under the footprint; the top stays out.
    assert np.all(z_base <= ground - 0.25 * height + 1e-9)
    assert np.all(z_base >= lowest - 0.25 * height - 1e-9)
    assert np.all(z_base + height > ground)
    assert np.mean(z_base + height > ground + 0.5 * height) > 0.95
    assert np.all((height > 0.3 * diameter) & (height < 0.7 * diameter))
    assert np.all((yaw >= 0) & (yaw < 2 * np.pi))
    assert np.all(shape_seed == np.floor(shape_seed))
    sand_under_rocks = terrain.sand_mask[np.clip(np.round((y + 30) / terrain.cell_m).astype(int), 0, 128),
                                         np.clip(np.round((x + 30) / terrain.cell_m).astype(int), 0, 128)]
    assert sand_under_rocks.mean() < 0.5 * terrain.sand_mask.mean()
