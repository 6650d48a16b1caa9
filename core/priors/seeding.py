"""Points lifted from depth priors, to seed Gaussians where the SfM points are sparse.

Triangulated SfM points cluster on texture: a sand sheet or a smooth crater floor gets few,
and 3DGS must then grow Gaussians there by densification, which takes many steps. A dense
depth prior already says where those surfaces are; lifting some of its pixels into the
scene gives the first Gaussians there at step 0 (docs/esgs.md, "Gaussians seeded from the
depth prior").
"""
from __future__ import annotations

from typing import Optional

import numpy as np


def lift_pixels(depth: np.ndarray, rows: np.ndarray, cols: np.ndarray, K: np.ndarray,
                world_to_camera: np.ndarray) -> np.ndarray:
    """World coordinates [M, 3] (float64) of pixels (``rows``, ``cols``) at their ``depth``.

    ``depth`` [H, W] is the distance along the camera's optical axis (z, OpenCV axes), as the
    rasterizer renders it and the prior maps store it; pixel (r, c) looks through its centre
    (c + 1/2, r + 1/2); ``K`` [3, 3]; ``world_to_camera`` [4, 4].
    """
    z = depth[rows, cols].astype(np.float64)
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    camera = np.stack([(cols + 0.5 - cx) / fx * z, (rows + 0.5 - cy) / fy * z, z], axis=-1)
    rotation = np.asarray(world_to_camera[:3, :3], dtype=np.float64)
    translation = np.asarray(world_to_camera[:3, 3], dtype=np.float64)
    return (camera - translation) @ rotation  # R^T (x - t), row by row


def sample_prior_pixels(valid: np.ndarray, count: int, rng: np.random.Generator,
                        weights: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of up to ``count`` distinct pixels where ``valid`` [H, W] holds, drawn
    with probability proportional to ``weights`` [H, W] (uniform when None; pixels of zero
    weight are never drawn)."""
    flat = np.flatnonzero(valid.reshape(-1))
    if weights is not None:
        p = np.asarray(weights, dtype=np.float64).reshape(-1)[flat]
        keep = p > 0
        flat, p = flat[keep], p[keep]
    else:
        p = None
    if count <= 0 or flat.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    if flat.size > count:
        flat = rng.choice(flat, size=count, replace=False, p=None if p is None else p / p.sum())
        flat.sort()  # raster order: the same points whatever order numpy's choice returns them in
    rows, cols = np.divmod(flat, valid.shape[1])
    return rows.astype(np.int64), cols.astype(np.int64)
