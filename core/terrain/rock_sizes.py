"""Rock size-frequency statistics of the Golombek-Rapp model (no terrain objects needed).

Kept apart from :mod:`.rocks` (which places rocks on a terrain) so that
:meth:`~.config.TerrainConfig.validate` can predict the rock count without importing the
terrain modules that themselves import the config.
"""
from __future__ import annotations

import numpy as np


def rock_q(abundance: float) -> float:
    """q(k) = 1.79 + 0.152 / k of the Golombek-Rapp model (1/m)."""
    return 1.79 + 0.152 / abundance


def cumulative_area_fraction(diameter_m: np.ndarray | float, abundance: float) -> np.ndarray:
    """F_k(D): fraction of the area covered by rocks with diameter >= D."""
    return abundance * np.exp(-rock_q(abundance) * np.asarray(diameter_m, dtype=np.float64))


def _diameter_table(abundance: float, min_diameter_m: float, max_diameter_m: float,
                    samples: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Diameters [S] (log-spaced) and the cumulative number per unit area below each [S]."""
    q = rock_q(abundance)
    diameters = np.geomspace(min_diameter_m, max_diameter_m, samples)
    density = 4.0 * abundance * q * np.exp(-q * diameters) / (np.pi * diameters ** 2)
    steps = 0.5 * (density[1:] + density[:-1]) * np.diff(diameters)
    return diameters, np.concatenate([[0.0], np.cumsum(steps)])


def expected_rock_count(abundance: float, min_diameter_m: float, max_diameter_m: float, area_m2: float) -> float:
    """Expected number of rocks with D in [min, max] on ``area_m2`` square metres."""
    if abundance <= 0:
        return 0.0
    _, cumulative = _diameter_table(abundance, min_diameter_m, max_diameter_m)
    return float(cumulative[-1] * area_m2)


def sample_rock_diameters(abundance: float, min_diameter_m: float, max_diameter_m: float, area_m2: float,
                          rng: np.random.Generator) -> np.ndarray:
    """Rock diameters [M] whose covered area follows F_k(D) - F_k(D_max) on ``area_m2``.

    M is the expected count rounded; diameters come from stratified inverse-CDF samples
    (one uniform draw in each of M equal probability strata), in random order.
    """
    if abundance <= 0:
        return np.zeros(0)
    diameters, cumulative = _diameter_table(abundance, min_diameter_m, max_diameter_m)
    count = int(round(cumulative[-1] * area_m2))
    if count == 0:
        return np.zeros(0)
    # Invert in log-diameter: the CDF is steep at small D and smooth in log D.
    strata = (np.arange(count) + rng.uniform(0.0, 1.0, size=count)) / count
    log_d = np.interp(strata * cumulative[-1], cumulative, np.log(diameters))
    return rng.permutation(np.exp(log_d))
