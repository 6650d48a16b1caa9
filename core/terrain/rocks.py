"""Rocks after the Golombek & Rapp (1997) rock-abundance model of Mars landing sites.

The cumulative fractional area covered by rocks of diameter >= D (metres) is

    F_k(D) = k exp(-q(k) D),   q(k) = 1.79 + 0.152 / k,

where k is the total rock abundance (F_k(0)). Differentiating gives the area covered by
rocks per unit diameter, k q exp(-q D); dividing by one rock's footprint pi D^2 / 4 gives the
number density per unit area and diameter, n(D) = 4 k q exp(-q D) / (pi D^2). We place rocks
with D in [D_min, D_max] only, so the placed rocks cover F_k(D) - F_k(D_max) of the area at
and above every D. Diameters are drawn by stratified inverse-CDF sampling of n(D), which
keeps the covered area close to the model even for a few hundred rocks.

Rocks are separate objects (the heightfield does not include them); each sits on the
surface, a share of its height buried (more on slopes), and prefers bedrock over sand.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .config import TerrainConfig
# the size-frequency maths lives apart so config validation can use it without a cycle
from .rock_sizes import (_diameter_table, cumulative_area_fraction, expected_rock_count, rock_q,  # noqa: F401
                         sample_rock_diameters)

if TYPE_CHECKING:
    from .heightfield import Terrain

ROCK_COLUMNS = ("x", "y", "z_base", "diameter_m", "height_m", "yaw_rad", "shape_seed")


def place_rocks(config: TerrainConfig, terrain: Terrain, rng: np.random.Generator) -> np.ndarray:
    """Rock table [M, 7]: x, y, z_base, diameter_m, height_m, yaw_rad, shape_seed.

    ``z_base`` is where the rock's bottom sits: ``rock_embed_fraction`` of its height below
    the ground at its centre, plus half the ground's drop across its footprint on slopes.
    """
    area = config.extent_m ** 2
    diameters = sample_rock_diameters(config.rock_abundance, config.rock_min_diameter_m,
                                      config.rock_max_diameter_m, area, rng)
    count = diameters.size
    if count == 0:
        return np.zeros((0, 7))
    # Positions: a cell drawn with weight favouring bedrock, then uniform inside the cell.
    weights = 1.0 - config.rock_sand_avoidance * terrain.sand_mask.astype(np.float64).ravel()
    weights = np.maximum(weights, 1e-6)
    cells = rng.choice(weights.size, size=count, p=weights / weights.sum())
    rows, cols = np.divmod(cells, terrain.resolution)
    cell = terrain.cell_m
    half = config.extent_m / 2
    x = np.clip(-half + (cols + rng.uniform(-0.5, 0.5, count)) * cell, -half, half)
    y = np.clip(-half + (rows + rng.uniform(-0.5, 0.5, count)) * cell, -half, half)
    heights = diameters * config.rock_height_ratio * rng.uniform(0.7, 1.3, count)
    yaw = rng.uniform(0.0, 2.0 * np.pi, count)
    shape_seed = rng.integers(0, 2 ** 31 - 1, count).astype(np.float64)
    centre = terrain.height_at(x, y)
    lowest = centre.copy()
    for angle in np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False):
        lowest = np.minimum(lowest, terrain.height_at(x + 0.5 * diameters * np.cos(angle),
                                                      y + 0.5 * diameters * np.sin(angle)))
    # Bury by the configured share below the centre, plus half the ground's drop across
    # the footprint: on a slope the rock then neither floats on its downhill side nor
    # disappears into the uphill side.
    z_base = centre - config.rock_embed_fraction * heights - 0.5 * (centre - lowest)
    return np.stack([x, y, z_base, diameters, heights, yaw, shape_seed], axis=1)
