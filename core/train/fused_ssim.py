"""D-SSIM for the training loss: one autograd node over Numba kernels on the CPU.

:func:`dssim` is the loss term's ``1 - mean(SSIM)`` of a rendered ``[H, W, C]`` image against its
target, with the 3DGS convention of :mod:`esgs.core.metrics.image` (11-tap Gaussian window,
sigma 1.5, zero padding, C1 = 0.01², C2 = 0.03²). On the CPU, for float32/float64 images whose
target needs no gradient, it runs :mod:`.ssim_kernels` (same values as the torch statement to
float rounding; tests compare values and gradients); elsewhere (a GPU, a target that needs a
gradient) the torch statement :func:`~esgs.core.metrics.image.ssim_map`.
"""
from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
import torch

from ..metrics.image import SSIM_CONSTANTS, gaussian_window_1d, ssim_map

WINDOW_SIZE = 11
WINDOW_SIGMA = 1.5


@lru_cache(maxsize=None)
def _window(dtype: np.dtype) -> tuple[np.ndarray, np.ndarray]:
    """The window's taps and (C1, C2) in ``dtype`` (made once per dtype, not every step)."""
    taps = gaussian_window_1d(WINDOW_SIZE, WINDOW_SIGMA, dtype=torch.float64).numpy().astype(dtype)
    return taps, np.asarray(SSIM_CONSTANTS, dtype)


class _FusedDSSIM(torch.autograd.Function):
    """1 - mean SSIM of image [H, W, C] against target (no gradient to the target)."""

    @staticmethod
    def forward(ctx: Any, image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        from .ssim_kernels import ssim_forward

        height, width, channels = image.shape
        x = image.detach().contiguous().numpy().reshape(height, width * channels)
        dtype = x.dtype
        y = target.detach().to(image.dtype).contiguous().numpy().reshape(height, width * channels)
        taps, constants = _window(dtype)
        totals, dmu, dxx, dxy = ssim_forward(x, y, taps, channels, constants)
        # the images as tensors (autograd then notices an in-place change before the backward),
        # the derivative maps as the kernel's own arrays
        ctx.save_for_backward(image, target)
        ctx.saved = (dmu, dxx, dxy, taps, channels)
        mean = float(totals.sum()) / x.size
        return torch.tensor(1.0 - mean, dtype=image.dtype)

    @staticmethod
    def backward(ctx: Any, grad_output: torch.Tensor) -> tuple[torch.Tensor | None, None]:
        from .ssim_kernels import ssim_backward

        image, target = ctx.saved_tensors
        dmu, dxx, dxy, taps, channels = ctx.saved
        shape = image.shape
        x = image.detach().contiguous().numpy().reshape(dmu.shape)
        y = target.detach().to(image.dtype).contiguous().numpy().reshape(dmu.shape)
        scale = np.asarray([-float(grad_output) / x.size], x.dtype)  # d(1 - mean S) = -dS / count
        grad = ssim_backward(x, y, dmu, dxx, dxy, taps, channels, scale)
        return torch.from_numpy(grad).reshape(shape), None


def dssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``1 - mean(SSIM)`` of ``image`` [H, W, C] against ``target`` (same shape), differentiable in ``image``."""
    fused = (image.device.type == "cpu" and image.dtype in (torch.float32, torch.float64) and image.dim() == 3
             and image.shape == target.shape and not target.requires_grad and min(image.shape[:2]) > 0)
    if fused:
        return _FusedDSSIM.apply(image, target)
    return 1.0 - ssim_map(image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None],
                          WINDOW_SIZE, WINDOW_SIGMA).mean()
