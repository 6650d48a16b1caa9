"""Pin a relative depth prior to the scene's scale with the SfM points its image observes.

A relative prior (NDN output) is known only up to a per-view scale and shift. Aligning it to
the rendered depth at every step (the fallback) keeps only its shape: a view whose Gaussians
all drift towards the camera still matches the aligned prior. Fitting scale and shift once to
the image's own triangulated points instead makes the prior metric in the scene's units, so
the depth loss also holds the surface at the right distance.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from .losses import fit_scale_shift

#: Fewer observed points than this and the fit is not trusted (the prior stays relative).
MIN_ALIGNMENT_POINTS = 20


@dataclass
class DepthAlignment:
    """Result of :func:`align_depth_to_points`.

    ``depth`` [H, W] is the metric prior (None when the fit was refused, see ``reason``);
    ``points`` the samples used; ``median_error`` the median |aligned - SfM| / SfM depth;
    ``contradicts``: refused because the prior and the points disagree (inverted or far off),
    not for want of points; such a prediction has failed.
    """

    depth: Optional[torch.Tensor]
    scale: float
    shift: float
    points: int
    median_error: float
    reason: str = ""
    contradicts: bool = False


def project_points(points_xyz: np.ndarray, K: torch.Tensor, viewmat: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """World points [M, 3] -> (pixel coordinates [M, 2] (x right, y down), camera depth z [M])."""
    world_to_camera = viewmat.double().numpy()
    camera = points_xyz @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = camera[:, 2]
    safe_z = np.where(np.abs(z) > 1e-12, z, 1e-12)
    intrinsics = K.double().numpy()
    u = intrinsics[0, 0] * camera[:, 0] / safe_z + intrinsics[0, 2]
    v = intrinsics[1, 1] * camera[:, 1] / safe_z + intrinsics[1, 2]
    return np.stack([u, v], axis=1), z


def align_depth_to_points(relative_depth: torch.Tensor, valid: torch.Tensor, K: torch.Tensor, viewmat: torch.Tensor,
                          points_xyz: np.ndarray, *, min_points: int = MIN_ALIGNMENT_POINTS) -> DepthAlignment:
    """Fit depth = s * relative + t to the SfM points seen by the view (robust, see ``fit_scale_shift``).

    Args:
        relative_depth: [H, W] prior, affine in true depth. valid: [H, W] bool, where it counts.
        K: [3, 3] intrinsics and viewmat: [4, 4] world-to-camera of the prior's resolution.
        points_xyz: [M, 3] world points the image observes.

    The fit is refused (``depth`` None) with fewer than ``min_points`` usable points, a
    scale that is not positive (the prior would invert near and far), or a median relative
    error above 50 % (the prior and the points disagree about the view).
    """
    height, width = relative_depth.shape
    if len(points_xyz) == 0:
        return DepthAlignment(None, 1.0, 0.0, 0, float("nan"), "the image observes no SfM points")
    pixels, z = project_points(np.asarray(points_xyz, np.float64), K, viewmat)
    columns = np.floor(pixels[:, 0]).astype(np.int64)
    rows = np.floor(pixels[:, 1]).astype(np.int64)
    inside = (z > 0) & (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
    columns, rows, z = columns[inside], rows[inside], z[inside]
    prior = relative_depth[rows, columns].double()
    usable = (valid[rows, columns] & (prior > 0)).numpy()
    count = int(usable.sum())
    if count < min_points:
        return DepthAlignment(None, 1.0, 0.0, count, float("nan"),
                              f"{count} SfM points fall on valid prior pixels (need {min_points})")
    x = prior[usable]
    y = torch.from_numpy(z[usable])
    scale, shift = fit_scale_shift(x, y, torch.ones_like(x, dtype=torch.bool))
    scale_f, shift_f = float(scale), float(shift)
    error = float(((scale * x + shift - y).abs() / y).median())
    if scale_f <= 0:
        return DepthAlignment(None, scale_f, shift_f, count, error, "the fitted scale is not positive",
                              contradicts=True)
    if error > 0.5:
        return DepthAlignment(None, scale_f, shift_f, count, error,
                              f"the prior disagrees with the SfM points (median error {error:.0%})", contradicts=True)
    aligned = (scale_f * relative_depth.double() + shift_f).to(relative_depth.dtype)
    aligned = torch.where(valid & (relative_depth > 0) & (aligned > 0), aligned, torch.zeros_like(aligned))
    return DepthAlignment(aligned, scale_f, shift_f, count, error)
