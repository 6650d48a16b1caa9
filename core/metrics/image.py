"""PSNR and SSIM between rendered and reference images (torch, differentiable).

Images are ``[B, 3, H, W]`` or ``[3, H, W]`` tensors with values in [0, 1] (data range 1).

SSIM follows the formulation used by 3DGS and ``pytorch-ssim``: an 11x11 Gaussian window
(sigma 1.5, normalised to sum 1) applied per channel, constants C1 = 0.01^2 and C2 = 0.03^2,
and *same-size* output with zero padding (the window is convolved with ``padding =
window_size // 2``). Zero padding darkens the local means within 5 pixels of the border, so
values there differ slightly from the "valid"-window SSIM of scikit-image; we keep the
3DGS convention so our numbers are comparable with published 3DGS-family results and the
training loss matches theirs. The window is separable, so it is applied as two 1D passes.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ..errors import ESGSError

__all__ = ["psnr", "ssim", "ssim_map", "gaussian_window_1d"]

_C1 = 0.01**2
_C2 = 0.03**2
#: (C1, C2) of the SSIM formula, for implementations outside this module (the training loss's kernels)
SSIM_CONSTANTS = (_C1, _C2)


def _as_batch(img: torch.Tensor, ref: torch.Tensor, what: str) -> tuple[torch.Tensor, torch.Tensor]:
    if not isinstance(img, torch.Tensor) or not isinstance(ref, torch.Tensor):
        raise ESGSError(f"{what}: images must be torch tensors, got {type(img).__name__} and {type(ref).__name__}")
    if img.shape != ref.shape:
        raise ESGSError(f"{what}: image shapes differ: {tuple(img.shape)} vs {tuple(ref.shape)}")
    if img.dim() == 3:
        img, ref = img.unsqueeze(0), ref.unsqueeze(0)
    if img.dim() != 4:
        raise ESGSError(f"{what}: expected [B, C, H, W] or [C, H, W] images, got shape {tuple(img.shape)}")
    return img, ref


def _reduce(values: torch.Tensor, reduction: str) -> torch.Tensor:
    if reduction == "mean":
        return values.mean()
    if reduction == "none":
        return values
    raise ESGSError(f"unknown reduction '{reduction}' (use 'mean' or 'none')")


def psnr(img: torch.Tensor, ref: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """Peak signal-to-noise ratio in dB for data range 1.

    img, ref: [B, C, H, W] or [C, H, W] in [0, 1]. The PSNR of each image (MSE over its
    channels and pixels) is computed first; ``reduction="mean"`` returns their mean (a
    scalar), ``"none"`` the per-image values [B]. Identical images give +inf.
    """
    img, ref = _as_batch(img, ref, "psnr")
    mse = (img - ref).pow(2).flatten(1).mean(dim=1)
    return _reduce(-10.0 * torch.log10(mse), reduction)


def gaussian_window_1d(window_size: int = 11, sigma: float = 1.5, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """The normalised 1D Gaussian taps [window_size] centred on the middle tap."""
    if window_size < 1 or window_size % 2 == 0:
        raise ESGSError(f"SSIM window size must be a positive odd number, got {window_size}")
    offsets = torch.arange(window_size, dtype=torch.float64, device=device) - window_size // 2
    taps = torch.exp(-(offsets**2) / (2.0 * sigma**2))
    return (taps / taps.sum()).to(dtype)


def _blur(x: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """Per-channel separable Gaussian blur with zero padding; x: [B, C, H, W] -> same shape."""
    channels = x.shape[1]
    half = taps.numel() // 2
    horizontal = taps.view(1, 1, 1, -1).repeat(channels, 1, 1, 1)
    vertical = taps.view(1, 1, -1, 1).repeat(channels, 1, 1, 1)
    x = F.conv2d(x, horizontal, padding=(0, half), groups=channels)
    return F.conv2d(x, vertical, padding=(half, 0), groups=channels)


def ssim_map(img: torch.Tensor, ref: torch.Tensor, window_size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Per-pixel, per-channel SSIM [B, C, H, W] (same-size, zero padding; see module docstring)."""
    img, ref = _as_batch(img, ref, "ssim")
    taps = gaussian_window_1d(window_size, sigma, dtype=img.dtype, device=img.device)
    # blur the five moments in one call: [img, ref, img^2, ref^2, img*ref] stacked on channels
    channels = img.shape[1]
    moments = _blur(torch.cat([img, ref, img * img, ref * ref, img * ref], dim=1), taps)
    mu_x, mu_y, xx, yy, xy = torch.split(moments, channels, dim=1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    sigma_xx, sigma_yy, sigma_xy = xx - mu_xx, yy - mu_yy, xy - mu_xy
    numerator = (2.0 * mu_xy + _C1) * (2.0 * sigma_xy + _C2)
    denominator = (mu_xx + mu_yy + _C1) * (sigma_xx + sigma_yy + _C2)
    return numerator / denominator


def ssim(
    img: torch.Tensor, ref: torch.Tensor, window_size: int = 11, sigma: float = 1.5, reduction: str = "mean"
) -> torch.Tensor:
    """Structural similarity, differentiable (used as the D-SSIM term of the training loss).

    img, ref: [B, C, H, W] or [C, H, W] in [0, 1]. ``reduction="mean"``: the mean of the SSIM
    map over batch, channels and pixels (a scalar, as 3DGS reports it; equal to the mean of
    the per-image values since all images share a size); ``"none"``: per-image means [B].
    """
    values = ssim_map(img, ref, window_size, sigma).flatten(1).mean(dim=1)
    return _reduce(values, reduction)
