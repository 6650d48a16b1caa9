"""Vectorised 2-D gradient noise and its fractal sums, evaluated on a regular grid.

Our own implementation (no noise package): random unit gradients on an integer lattice,
a quintic fade between the four surrounding lattice corners. Values are roughly in
[-0.7, 0.7] with zero mean; :func:`fractal_noise` rescales to unit standard deviation.
"""
from __future__ import annotations

import numpy as np


def _fade(t: np.ndarray) -> np.ndarray:
    # Quintic fade: continuous first and second derivatives, so no grid-aligned creases.
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


def gradient_noise(coords_x: np.ndarray, coords_y: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Gradient noise on the grid ``coords_y[:, None] x coords_x[None, :]`` (lattice units).

    coords_x: [W] increasing lattice coordinates of the columns; coords_y: [H] of the rows.
    Returns [H, W] float64. A fresh random lattice is drawn from ``rng`` per call.
    """
    x0 = np.floor(coords_x).astype(np.int64)
    y0 = np.floor(coords_y).astype(np.int64)
    offset_x, offset_y = x0.min(), y0.min()
    x0 -= offset_x
    y0 -= offset_y
    nx, ny = int(x0.max()) + 2, int(y0.max()) + 2
    angles = rng.uniform(0.0, 2.0 * np.pi, size=(ny, nx))
    grad_x, grad_y = np.cos(angles), np.sin(angles)
    fx = (coords_x - np.floor(coords_x))[None, :]
    fy = (coords_y - np.floor(coords_y))[:, None]

    def corner(rows: np.ndarray, cols: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
        # The sample points form a grid, so gather rows then columns (two cheap takes)
        # instead of one 2-D fancy index.
        gx = grad_x.take(rows, axis=0).take(cols, axis=1)
        gy = grad_y.take(rows, axis=0).take(cols, axis=1)
        return gx * dx + gy * dy

    n00 = corner(y0, x0, fx, fy)
    n10 = corner(y0, x0 + 1, fx - 1.0, fy)
    n01 = corner(y0 + 1, x0, fx, fy - 1.0)
    n11 = corner(y0 + 1, x0 + 1, fx - 1.0, fy - 1.0)
    u, v = _fade(fx), _fade(fy)
    top = n00 + u * (n10 - n00)
    bottom = n01 + u * (n11 - n01)
    return top + v * (bottom - top)


def fractal_noise(coords_x_m: np.ndarray, coords_y_m: np.ndarray, rng: np.random.Generator, *,
                  wavelength_m: float, octaves: int, roughness: float = 0.5, ridged: float = 0.0,
                  min_wavelength_m: float = 0.0) -> np.ndarray:
    """Fractional Brownian motion (optionally mixed with ridged noise), unit std, zero mean.

    coords_x_m: [W], coords_y_m: [H] metres. The coarsest octave has ``wavelength_m``; each
    next octave halves it and multiplies the amplitude by ``roughness``. Octaves shorter
    than ``min_wavelength_m`` (e.g. two grid cells) are skipped, as they would only alias.
    ``ridged`` in [0, 1] blends in ridged noise (1 - |n|)^2, which gives sharp crests.
    Returns [H, W] float64.
    """
    total = np.zeros((coords_y_m.size, coords_x_m.size))
    amplitude, wavelength = 1.0, wavelength_m
    for _ in range(octaves):
        if wavelength < min_wavelength_m:
            break
        # A random sub-lattice shift per octave keeps lattice corners of octaves from lining up.
        shift_x, shift_y = rng.uniform(0.0, 1000.0, size=2)
        layer = gradient_noise(coords_x_m / wavelength + shift_x, coords_y_m / wavelength + shift_y, rng)
        if ridged > 0.0:
            ridge = (1.0 - np.abs(layer) * 1.6) ** 2
            layer = (1.0 - ridged) * layer + ridged * (ridge - 0.5)
        total += amplitude * layer
        amplitude *= roughness
        wavelength *= 0.5
    total -= total.mean()
    std = total.std()
    return total / std if std > 0 else total
