"""Impact craters: power-law diameters, bowl + raised rim + ejecta, fresh to degraded.

Size-frequency: the cumulative number of craters larger than D follows N(>D) ~ D^-b on
[D_min, D_max] (a truncated Pareto law), sampled by inverting its CDF.

Shape of one crater, as a function of s = r / R (R = D / 2), added to the surface:

* inside (s < 1): a bowl from the floor at -depth up to the rim crest at +rim,
  z = -depth + (depth + rim) s^p, with p = 2 (fresh, parabolic) growing to 4 (degraded,
  flat-floored as if infilled);
* outside (1 < s < 3): the ejecta blanket, thickness rim * s^-3, tapered to 0 at s = 3;
* degradation g in [0, 1] makes the crater shallower (depth * (1 - 0.8 g)), lowers the
  rim (rim * (1 - 0.85 g)) and rounds the crest (the radial profile is smoothed more).

Craters are stamped oldest (most degraded) first; a crater's bowl replaces the older
surface inside it (fully for a fresh crater, less for degraded ones), so young craters
wipe out older small ones. Each crater touches only its local window (3 R around the
centre), which keeps hundreds of craters on a 513 x 513 grid well under a second.
"""
from __future__ import annotations

import numpy as np

from .config import TerrainConfig

EJECTA_EXTENT = 3.0  # ejecta blanket radius in crater radii
_PROFILE_SAMPLES = 600


def sample_crater_diameters(count: int, min_diameter_m: float, max_diameter_m: float, exponent: float,
                            rng: np.random.Generator) -> np.ndarray:
    """Diameters [count] with cumulative N(>D) ~ D^-exponent on [min, max] (inverse CDF)."""
    u = rng.uniform(0.0, 1.0, size=count)
    low, high = min_diameter_m ** -exponent, max_diameter_m ** -exponent
    return (low - u * (low - high)) ** (-1.0 / exponent)


def fit_sfd_exponent(diameters: np.ndarray, min_diameter_m: float, max_diameter_m: float) -> float:
    """Maximum-likelihood b of a truncated power law N(>D) ~ D^-b on [min, max].

    Solves d/db log L = 0 for the density b D^(-b-1) / (min^-b - max^-b) by bisection.
    """
    diameters = np.asarray(diameters, dtype=np.float64)
    mean_log = np.mean(np.log(diameters / min_diameter_m))
    ratio = max_diameter_m / min_diameter_m

    def score(b: float) -> float:
        # d/db of the mean log-likelihood; decreasing in b.
        t = ratio ** -b
        return 1.0 / b - mean_log - t * np.log(ratio) / (1.0 - t)

    low, high = 1e-4, 50.0
    for _ in range(200):
        mid = 0.5 * (low + high)
        if score(mid) > 0:
            low = mid
        else:
            high = mid
    return 0.5 * (low + high)


def sample_craters(config: TerrainConfig, rng: np.random.Generator) -> np.ndarray:
    """Crater table [K, 5]: x, y, diameter_m, depth_m, degradation (0 fresh .. 1 degraded).

    Centres are uniform over the terrain square; depth is the floor's depth below the
    surrounding surface after degradation.
    """
    count = config.crater_count
    if count == 0:
        return np.zeros((0, 5))
    diameters = sample_crater_diameters(count, config.crater_min_diameter_m, config.crater_max_diameter_m,
                                        config.crater_sfd_exponent, rng)
    half = config.extent_m / 2
    x = rng.uniform(-half, half, size=count)
    y = rng.uniform(-half, half, size=count)
    degradation = rng.uniform(config.crater_degradation_min, config.crater_degradation_max, size=count)
    depth = config.crater_depth_ratio * diameters * (1.0 - 0.8 * degradation)
    # Largest first, so a reader of the table sees the dominant craters on top.
    order = np.argsort(-diameters, kind="stable")
    return np.stack([x, y, diameters, depth, degradation], axis=1)[order]


def crater_profile(s: np.ndarray, depth: float, rim: float, degradation: float) -> np.ndarray:
    """Height change at normalised radii ``s = r / R`` [N] for one crater (metres)."""
    table_s = np.linspace(0.0, EJECTA_EXTENT, _PROFILE_SAMPLES)
    power = 2.0 + 2.0 * degradation
    inside = -depth + (depth + rim) * np.minimum(table_s, 1.0) ** power
    outside_s = np.maximum(table_s, 1.0)
    taper = np.clip((EJECTA_EXTENT - outside_s) / (EJECTA_EXTENT - 2.0), 0.0, 1.0)
    taper = taper * taper * (3.0 - 2.0 * taper)
    outside = rim * outside_s ** -3.0 * taper
    table = np.where(table_s <= 1.0, inside, outside)
    # Round the crest: Gaussian smoothing along s, wider for degraded craters.
    sigma = (0.02 + 0.2 * degradation) * (_PROFILE_SAMPLES - 1) / EJECTA_EXTENT
    half_width = int(np.ceil(3 * sigma))
    kernel = np.exp(-0.5 * (np.arange(-half_width, half_width + 1) / sigma) ** 2)
    kernel /= kernel.sum()
    # Mirror at s = 0 (the profile is even in r) and hold the far end at 0.
    padded = np.concatenate([table[half_width:0:-1], table, np.zeros(half_width)])
    smoothed = np.convolve(padded, kernel, mode="valid")
    smoothed[-1] = 0.0
    return np.interp(s, table_s, smoothed, right=0.0)


def apply_craters(heights: np.ndarray, craters: np.ndarray, extent_m: float, rim_ratio: float) -> None:
    """Stamp every crater of ``craters`` [K, 5] into ``heights`` [R, R] in place (metres).

    Craters are stamped oldest (most degraded) first. Inside its bowl a crater replaces what
    was there with its own floor: the older surface is blended toward a plane fitted
    around the rim (which keeps a regional tilt) with weight (1 - degradation), so a fresh
    crater wipes out older small craters inside it, and an old degraded one has since been
    roughened again like its surroundings.
    """
    resolution = heights.shape[0]
    cell = extent_m / (resolution - 1)
    origin = -extent_m / 2
    order = np.argsort(-craters[:, 4], kind="stable") if len(craters) else np.zeros(0, dtype=np.int64)
    for x, y, diameter, depth, degradation in craters[order]:
        radius = diameter / 2
        reach = EJECTA_EXTENT * radius
        col0 = max(int(np.floor((x - reach - origin) / cell)), 0)
        col1 = min(int(np.ceil((x + reach - origin) / cell)) + 1, resolution)
        row0 = max(int(np.floor((y - reach - origin) / cell)), 0)
        row1 = min(int(np.ceil((y + reach - origin) / cell)) + 1, resolution)
        if col0 >= col1 or row0 >= row1:
            continue
        xs = origin + np.arange(col0, col1) * cell - x
        ys = origin + np.arange(row0, row1) * cell - y
        s = np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2) / radius
        window = heights[row0:row1, col0:col1]
        erase = 1.0 - degradation
        if erase > 0:
            _erase_interior(window, xs, ys, s, erase)
        rim = rim_ratio * diameter * (1.0 - 0.85 * degradation)
        window += crater_profile(s, depth, rim, degradation)


def _erase_interior(window: np.ndarray, xs: np.ndarray, ys: np.ndarray, s: np.ndarray, strength: float) -> None:
    """Blend the surface inside s < 1 toward a plane fitted on the ring 0.9 < s < 1.3, in place."""
    ring = (s > 0.9) & (s < 1.3)
    if ring.sum() < 6:
        return  # crater too small for the grid (or cut off at the edge): nothing to fit
    x_grid, y_grid = np.broadcast_to(xs[None, :], s.shape), np.broadcast_to(ys[:, None], s.shape)
    design = np.stack([np.ones(int(ring.sum())), x_grid[ring], y_grid[ring]], axis=1)
    coefficients, *_ = np.linalg.lstsq(design, window[ring], rcond=None)
    plane = coefficients[0] + coefficients[1] * x_grid + coefficients[2] * y_grid
    # Full replacement well inside the bowl, fading out toward the rim crest.
    fade = np.clip((1.0 - s) / 0.4, 0.0, 1.0)
    weight = strength * fade * fade * (3.0 - 2.0 * fade)
    window += weight * (plane - window)
