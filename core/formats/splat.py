"""The ``.splat`` format of antimatter15's WebGL viewer (also opened by SuperSplat and most web viewers).

No header; 32 bytes per Gaussian, little-endian:

- 3 float32: position x, y, z;
- 3 float32: axis scales, activated (``exp`` of the PLY's log-scales);
- 4 uint8: colour R, G, B, A: ``0.5 + C0 * f_dc`` (the degree-0 SH colour, ``C0 = 0.28209479``)
  and ``sigmoid(opacity)``, times 255, clipped to 0..255;
- 4 uint8: the rotation quaternion, w first: ``(q / |q|) * 128 + 128``, clipped to 0..255.

Gaussians are sorted by descending ``exp(scale_0 + scale_1 + scale_2) * alpha`` (big opaque
ones first), as antimatter15's ``convert.py`` writes them and viewers that stream the file
expect. Only the base colour is kept: the higher SH bands (view-dependent colour) have no place
in the format. We round to the nearest uint8 where ``convert.py`` truncates (a difference of
at most one step).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..io_utils import atomic_path
from .ply import GaussianPly

__all__ = ["SH_C0", "SPLAT_DTYPE", "splat_order", "splat_records", "write_splat"]

#: The degree-0 real spherical-harmonic constant, 1 / (2 sqrt(pi)).
SH_C0 = 0.28209479177387814

#: One record of a ``.splat`` file.
SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])


def splat_order(gaussians: GaussianPly) -> np.ndarray:
    """Indices by descending ``exp(sum of log-scales) * sigmoid(opacity)`` (stable for ties)."""
    log_scales = gaussians.log_scales.astype(np.float64)
    logits = gaussians.opacity_logit.astype(np.float64)
    with np.errstate(over="ignore"):
        alpha = 1.0 / (1.0 + np.exp(-logits))
        key = np.exp(log_scales.sum(axis=1)) * alpha
    return np.argsort(-key, kind="stable")


def splat_records(gaussians: GaussianPly) -> np.ndarray:
    """The ``.splat`` records of ``gaussians`` (a structured array of :data:`SPLAT_DTYPE`), sorted."""
    order = splat_order(gaussians)
    records = np.empty(len(gaussians), dtype=SPLAT_DTYPE)
    records["position"] = gaussians.means[order]
    records["scale"] = gaussians.scales()[order]
    colour = 0.5 + SH_C0 * gaussians.sh_dc[order].astype(np.float64)
    rgba = np.concatenate([colour, gaussians.opacities()[order, None].astype(np.float64)], axis=1)
    records["rgba"] = _to_uint8(rgba * 255.0)
    records["rotation"] = _to_uint8(gaussians.rotations_normalised()[order].astype(np.float64) * 128.0 + 128.0)
    return records


def write_splat(path: str | Path, gaussians: GaussianPly) -> None:
    """Write ``gaussians`` as a ``.splat`` file at ``path``, atomically."""
    data = splat_records(gaussians).tobytes()
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())


def _to_uint8(values: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.nan_to_num(values, nan=0.0)), 0, 255).astype(np.uint8)
