"""Differentiable Gaussian rasterization (CPU Numba kernels, dense torch reference, gsplat CUDA).

Public entry point: :func:`rasterization`. See docs/rasterizer.md.
"""
from .api import BACKENDS, rasterization

__all__ = ["BACKENDS", "rasterization"]
