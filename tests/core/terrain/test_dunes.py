"""Dunes: orientation follows the wind, lee faces are steep and face downwind, sand only."""
from __future__ import annotations

import math

import numpy as np
import pytest

from esgs.core.terrain import TerrainConfig, generate_terrain
from esgs.core.terrain.dunes import asymmetric_wave


def dune_config(wind: float, **changes) -> TerrainConfig:
    values = dict(resolution=257, extent_m=120.0, relief_amplitude_m=0.0, sand_fraction=1.0,
                  dune_amplitude_m=2.0, dune_wavelength_m=12.0, dune_asymmetry=0.75, wind_azimuth_deg=wind)
    values.update(changes)
    return TerrainConfig(**values)


def dominant_wave_vector(field: np.ndarray, cell: float) -> tuple[float, float]:
    """Azimuth (degrees, modulo 180) and wavelength (m) of the strongest Fourier component."""
    spectrum = np.abs(np.fft.fft2((field - field.mean()) * np.outer(np.hanning(field.shape[0]), np.hanning(field.shape[1]))))
    spectrum[0, 0] = 0
    row, col = np.unravel_index(np.argmax(spectrum), spectrum.shape)
    ky = np.fft.fftfreq(field.shape[0], cell)[row]
    kx = np.fft.fftfreq(field.shape[1], cell)[col]
    return math.degrees(math.atan2(ky, kx)) % 180.0, 1.0 / math.hypot(kx, ky)


def angle_gap(a: float, b: float) -> float:
    gap = abs(a - b) % 180.0
    return min(gap, 180.0 - gap)


@pytest.mark.parametrize("wind", [0.0, 30.0, 75.0, 135.0, 250.0])
def test_dune_wave_vector_points_along_the_wind(wind):
    terrain = generate_terrain(dune_config(wind), seed=1)
    azimuth, wavelength = dominant_wave_vector(terrain.components["dunes"], terrain.cell_m)
    assert angle_gap(azimuth, wind) < 8.0
    assert wavelength == pytest.approx(12.0, rel=0.2)


def test_lee_faces_are_steep_and_face_downwind():
    wind = 40.0
    terrain = generate_terrain(dune_config(wind), seed=2)
    d_x, d_y = np.gradient(terrain.components["dunes"].astype(np.float64), terrain.cell_m)
    along = d_x[None] * 0 + d_x * math.cos(math.radians(wind)) + d_y * math.sin(math.radians(wind))
    along = along.ravel()
    # Going downwind the surface drops steeply (lee) and rises gently (stoss).
    assert np.percentile(along, 2) < -1.8 * np.percentile(along, 98)
    assert np.mean(along ** 3) < 0


def test_asymmetric_wave_profile():
    phase = np.linspace(0, 1, 1001)
    wave = asymmetric_wave(phase, 0.75)
    assert wave.min() == pytest.approx(-0.5) and wave.max() == pytest.approx(0.5)
    assert phase[np.argmax(wave)] == pytest.approx(0.75, abs=1e-3)
    np.testing.assert_allclose(asymmetric_wave(phase + 3.0, 0.75), wave, atol=1e-9)


def test_dunes_only_on_sand():
    config = dune_config(0.0, sand_fraction=0.3, relief_amplitude_m=1.0, relief_wavelength_m=40.0)
    terrain = generate_terrain(config, seed=3)
    dunes = np.abs(terrain.components["dunes"])
    bedrock = terrain.sand_mask < 0.05
    sand = terrain.sand_mask > 0.95
    assert dunes[bedrock].max() < 0.05 * 2.0
    assert dunes[sand].mean() > 0.3


def test_ripples_add_a_short_wavelength():
    config = dune_config(90.0, dune_amplitude_m=0.0, ripple_amplitude_m=0.1, ripple_wavelength_m=2.0)
    terrain = generate_terrain(config, seed=4)
    azimuth, wavelength = dominant_wave_vector(terrain.components["dunes"], terrain.cell_m)
    assert angle_gap(azimuth, 90.0) < 10.0 and wavelength == pytest.approx(2.0, rel=0.2)


def test_wide_smoothing_keeps_mass_and_spread():
    from esgs.core.terrain.dunes import smooth
    impulse = np.zeros((301, 301))
    impulse[150, 150] = 1.0
    for sigma in (2.0, 12.0):
        blurred = smooth(impulse, sigma)
        assert blurred.sum() == pytest.approx(1.0)
        offsets = (np.arange(301) - 150.0) ** 2
        assert (blurred * offsets[None, :]).sum() == pytest.approx(sigma ** 2, rel=0.12)
        assert (blurred * offsets[:, None]).sum() == pytest.approx(sigma ** 2, rel=0.12)
