"""Transverse dunes and ripples: periodic asymmetric ridges across the wind, and the sand mask.

Along the wind coordinate u (metres, increasing downwind) one period rises gently over the
stoss side (a share ``asymmetry`` of the wavelength) and drops over the steeper lee side.
Crests run perpendicular to the wind, so the dominant wave vector of the dune component
points along the wind azimuth. Slow noise in the phase makes crests sinuous and noise in
the amplitude keeps them from looking machined.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from .config import TerrainConfig
from .noise import fractal_noise


def asymmetric_wave(phase: np.ndarray, asymmetry: float) -> np.ndarray:
    """Ridge profile in [-0.5, 0.5] for ``phase`` in periods; crest at ``asymmetry`` of each period."""
    fraction = phase - np.floor(phase)
    rising = fraction / asymmetry
    falling = (1.0 - fraction) / (1.0 - asymmetry)
    ramp = np.where(fraction < asymmetry, rising, falling)
    # Smoothstep rounds crest and trough (zero slope there) without moving them.
    return ramp * ramp * (3.0 - 2.0 * ramp) - 0.5


def ridge_field(coords_x_m: np.ndarray, coords_y_m: np.ndarray, rng: np.random.Generator, *,
                amplitude_m: float, wavelength_m: float, asymmetry: float, sinuosity: float,
                wind_azimuth_deg: float) -> np.ndarray:
    """Height [H, W] of asymmetric ridges, crest-to-trough ``amplitude_m``, crests across the wind."""
    azimuth = np.radians(wind_azimuth_deg)
    downwind = coords_x_m[None, :] * np.cos(azimuth) + coords_y_m[:, None] * np.sin(azimuth)
    wander = fractal_noise(coords_x_m, coords_y_m, rng, wavelength_m=4.0 * wavelength_m, octaves=2)
    strength = fractal_noise(coords_x_m, coords_y_m, rng, wavelength_m=3.0 * wavelength_m, octaves=2)
    phase = downwind / wavelength_m + sinuosity * wander
    return amplitude_m * np.clip(1.0 + 0.2 * strength, 0.4, 1.6) * asymmetric_wave(phase, asymmetry)


def dune_component(config: TerrainConfig, coords_x_m: np.ndarray, coords_y_m: np.ndarray,
                   rng: np.random.Generator) -> np.ndarray:
    """Dunes plus ripples [H, W] (metres), before masking by sand; zeros when both are off."""
    total = np.zeros((coords_y_m.size, coords_x_m.size))
    if config.dune_amplitude_m > 0:
        total += ridge_field(coords_x_m, coords_y_m, rng, amplitude_m=config.dune_amplitude_m,
                             wavelength_m=config.dune_wavelength_m, asymmetry=config.dune_asymmetry,
                             sinuosity=config.dune_sinuosity, wind_azimuth_deg=config.wind_azimuth_deg)
    if config.ripple_amplitude_m > 0:
        # Ripples: same wind, milder asymmetry, a little more waviness.
        total += ridge_field(coords_x_m, coords_y_m, rng, amplitude_m=config.ripple_amplitude_m,
                             wavelength_m=config.ripple_wavelength_m, asymmetry=0.6,
                             sinuosity=0.25, wind_azimuth_deg=config.wind_azimuth_deg)
    return total


def smooth(field: np.ndarray, sigma_cells: float) -> np.ndarray:
    """Gaussian-like blur [H, W]; wide blurs use three box passes, whose cost does not grow with width."""
    if sigma_cells < 4.0:
        return ndimage.gaussian_filter(field, sigma=sigma_cells, mode="nearest")
    # Three box filters of width w have variance 3 (w^2 - 1) / 12.
    width = int(round(np.sqrt(4.0 * sigma_cells ** 2 + 1.0)))
    width += 1 - width % 2
    result = field
    for _ in range(3):
        result = ndimage.uniform_filter(result, size=width, mode="nearest")
    return result


def sand_mask(config: TerrainConfig, heights: np.ndarray, coords_x_m: np.ndarray, coords_y_m: np.ndarray,
              rng: np.random.Generator) -> np.ndarray:
    """Sand cover [H, W] in [0, 1] (1 = sand): low ground and a noise field, ~``sand_fraction`` of the area."""
    shape = heights.shape
    if config.sand_fraction >= 0.999:
        return np.ones(shape)
    if config.sand_fraction <= 0.001:
        return np.zeros(shape)
    cell = config.extent_m / (config.resolution - 1)
    # Lowness relative to the neighbourhood (a few metres), so sand pools in craters and
    # troughs even on a regional slope.
    sigma_cells = max(4.0 / cell, 1.0)
    local = heights - smooth(heights, sigma_cells * 3)
    local = smooth(local, max(0.5 / cell, 0.5))
    std = local.std()
    lowness = -local / std if std > 0 else np.zeros(shape)
    patches = fractal_noise(coords_x_m, coords_y_m, rng, wavelength_m=max(config.extent_m / 4, 8 * cell),
                            octaves=4, min_wavelength_m=2 * cell)
    score = config.sand_low_bias * lowness + (1.0 - config.sand_low_bias) * patches
    threshold = np.quantile(score, 1.0 - config.sand_fraction)
    softness = 0.15 * score.std()
    return 1.0 / (1.0 + np.exp(-(score - threshold) / softness))
