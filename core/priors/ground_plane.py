"""A view's near ground as a plane: the guide for the labels' holes where the network is weak.

On rover-height views stereo leaves the ground right in front of the camera empty (seen by one
view, or too oblique for the neighbours), and a learned network's shape is poor there: pinned
and level-corrected, it is often more than 25 % off (measured on the generator's rover scenes,
docs/priors.md "The near ground as a plane"). The labelled ground a few
metres farther is nearly planar at that scale, and a plane through it extends to the near
ground well: a ray that meets the plane steeply gets a depth that a small tilt of the plane
barely moves. Near the horizon the opposite holds (a grazing ray's depth swings with the
slightest tilt), so the plane is used only where its rays meet it at more than a set angle,
and ``priors/auto`` uses it only in views that look across the ground and whose nearer labels
lie on it (:attr:`ViewPlane.inlier_share`): inside a crater a plane would cut through the ground.

The plane is fitted in the camera frame, robustly (RANSAC, then a least-squares refit on its
inliers), to the nearer half of the view's labelled pixels: the far half is where the terrain
curves away and where the labels themselves are least sure.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

#: Fewest labelled pixels to fit a plane from.
MIN_PLANE_PIXELS = 50
#: RANSAC hypotheses per view (deterministic: a fixed seed).
RANSAC_ITERATIONS = 200
#: A labelled point is an inlier when its distance to the plane is under this share of its range.
INLIER_TOLERANCE = 0.02
#: Share of the labelled pixels (the nearest) the plane is fitted to.
NEAR_SHARE = 0.5


@dataclass(frozen=True)
class ViewPlane:
    """``normal . X = offset`` in the camera frame (OpenCV axes), with the share of the fitted
    points within :data:`INLIER_TOLERANCE` of it."""

    normal: np.ndarray
    offset: float
    inlier_share: float


def pixel_rays(intrinsics: np.ndarray, height: int, width: int) -> np.ndarray:
    """[H, W, 3] camera-frame rays with z = 1 through the pixel centres (COLMAP's +0.5)."""
    fx, fy, cx, cy = (float(intrinsics[0, 0]), float(intrinsics[1, 1]), float(intrinsics[0, 2]),
                      float(intrinsics[1, 2]))
    rows, columns = np.mgrid[0:height, 0:width]
    return np.stack([(columns + 0.5 - cx) / fx, (rows + 0.5 - cy) / fy, np.ones((height, width))], axis=-1)


def fit_view_plane(depth: np.ndarray, valid: np.ndarray, intrinsics: np.ndarray, *, seed: int = 0,
                   max_points: int = 20_000) -> Optional[ViewPlane]:
    """The plane through the nearer :data:`NEAR_SHARE` of the pixels ``valid`` of z-depth
    ``depth`` [H, W] seen with ``intrinsics`` [3, 3]; None with fewer than
    :data:`MIN_PLANE_PIXELS` of them or when no three of them span a plane."""
    height, width = depth.shape
    if int(valid.sum()) < MIN_PLANE_PIXELS:
        return None
    rays = pixel_rays(intrinsics, height, width)[valid]
    values = depth[valid].astype(np.float64)
    near = values <= np.quantile(values, NEAR_SHARE)
    points = rays[near] * values[near, None]
    generator = np.random.default_rng(seed)
    if len(points) > max_points:  # a full-size view has ~10^5 labelled pixels: a sample fits as well
        points = points[generator.choice(len(points), max_points, replace=False)]
    if len(points) < 3:
        return None
    ranges = np.linalg.norm(points, axis=1)
    best: Optional[np.ndarray] = None
    for _ in range(RANSAC_ITERATIONS):
        sample = points[generator.choice(len(points), 3, replace=False)]
        normal = np.cross(sample[1] - sample[0], sample[2] - sample[0])
        length = np.linalg.norm(normal)
        if length < 1e-12:
            continue
        normal /= length
        inliers = np.abs(points @ normal - normal @ sample[0]) < INLIER_TOLERANCE * ranges
        if best is None or inliers.sum() > best.sum():
            best = inliers
    if best is None or best.sum() < 3:
        return None
    centre = points[best].mean(axis=0)
    _, _, vt = np.linalg.svd(points[best] - centre, full_matrices=False)
    normal = vt[2]
    offset = float(normal @ centre)
    if offset < 0:  # orient the normal away from the camera: rays in front meet it at positive depth
        normal, offset = -normal, -offset
    share = float(np.mean(np.abs(points @ normal - offset) < INLIER_TOLERANCE * ranges))
    return ViewPlane(normal=normal, offset=offset, inlier_share=share)


def plane_depth(plane: ViewPlane, intrinsics: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(z-depth [H, W] where each pixel's ray meets ``plane``, 0 where it does not in front of
    the camera; the angle in degrees [H, W] between each ray and the plane)."""
    rays = pixel_rays(intrinsics, height, width)
    facing = rays @ plane.normal
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(facing > 1e-9, plane.offset / facing, 0.0)
    angle = np.degrees(np.arcsin(np.clip(np.abs(facing) / np.linalg.norm(rays, axis=-1), 0.0, 1.0)))
    return depth.astype(np.float32), angle.astype(np.float32)
