"""Differentiable Gaussian rasterization (CPU Numba kernels, dense torch reference, gsplat CUDA).

Public entry point: :func:`rasterization`. See docs/rasterizer.md.
"""
from .api import BACKENDS, MEDIAN_SURFACE_BACKENDS, rasterization

__all__ = ["BACKENDS", "MEDIAN_SURFACE_BACKENDS", "rasterization"]
