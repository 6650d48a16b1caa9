"""Labels that look through a gap of a reconstructed mesh (``--reconstruct``).

The 2.5D mesher (:mod:`.reconstruct`) removes the long triangles that would bridge the
places stereo left empty (low texture near the rover, occlusion shadows), so gaps stay
gaps. A camera ray that enters such a gap passes under the terrain and hits whatever lies
behind: on a hillside view that is ground tens of metres farther than the true surface, a
label 2-10x too deep that the depth prior would then pull Gaussians towards.

This module finds those pixels: the removed triangles are kept as a *gap mesh*
(``mesh/reconstructed_gaps.ply``), its depth is z-buffered into each view, and a label
whose depth lies behind a gap triangle on its own ray is marked as looking through a gap.
The label writer drops those pixels (no label) before hole filling.
"""
from __future__ import annotations

import numpy as np

from ..formats.scene_dir import gap_mesh_path

__all__ = ["gap_mesh_path", "through_gap", "zbuffer_depth"]


def _clip_near(corners: np.ndarray, near: float) -> list[np.ndarray]:
    """Clip one camera-frame triangle [3, 3] against the plane z = near; return the
    triangles (0, 1 or 2) of the part in front, as a fan."""
    inside = corners[:, 2] >= near
    if inside.all():
        return [corners]
    if not inside.any():
        return []
    polygon = []
    for i in range(3):
        current, following = corners[i], corners[(i + 1) % 3]
        if current[2] >= near:
            polygon.append(current)
        if (current[2] >= near) != (following[2] >= near):
            t = (near - current[2]) / (following[2] - current[2])
            polygon.append(current + t * (following - current))
    return [np.stack([polygon[0], polygon[k], polygon[k + 1]]) for k in range(1, len(polygon) - 1)]


def zbuffer_depth(vertices: np.ndarray, triangles: np.ndarray, K: np.ndarray, world_to_camera: np.ndarray,
                  width: int, height: int, *, near: float = 1e-6) -> np.ndarray:
    """Nearest depth (camera z, OpenCV axes) of a triangle mesh at every pixel centre.

    vertices [V, 3] world; triangles [F, 3]; K [3, 3]; world_to_camera [4, 4]. Pixel (x, y)
    is sampled at (x + 0.5, y + 0.5) as in COLMAP. Triangles are clipped at z = ``near``.
    Returns [height, width] float64, ``inf`` where no triangle covers the pixel. Meant for
    small meshes (a gap mesh has hundreds to a few thousand triangles): one numpy pass per
    triangle over its bounding box.
    """
    depth = np.full((height, width), np.inf)
    if len(triangles) == 0:
        return depth
    rotation, translation = world_to_camera[:3, :3], world_to_camera[:3, 3]
    camera_points = np.asarray(vertices, np.float64) @ rotation.T + translation
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for triangle in np.asarray(triangles, np.int64):
        for corners in _clip_near(camera_points[triangle], near):
            z = corners[:, 2]
            u = fx * corners[:, 0] / z + cx
            v = fy * corners[:, 1] / z + cy
            x0, x1 = max(int(np.floor(u.min() - 0.5)), 0), min(int(np.ceil(u.max() - 0.5)), width - 1)
            y0, y1 = max(int(np.floor(v.min() - 0.5)), 0), min(int(np.ceil(v.max() - 0.5)), height - 1)
            if x0 > x1 or y0 > y1:
                continue
            area = (u[1] - u[0]) * (v[2] - v[0]) - (u[2] - u[0]) * (v[1] - v[0])
            if abs(area) < 1e-12:
                continue  # seen edge-on: covers no pixel centre
            xs, ys = np.meshgrid(np.arange(x0, x1 + 1) + 0.5, np.arange(y0, y1 + 1) + 0.5)
            # screen-space barycentrics; 1/z is affine in screen space for a planar triangle
            b1 = ((xs - u[0]) * (v[2] - v[0]) - (u[2] - u[0]) * (ys - v[0])) / area
            b2 = ((u[1] - u[0]) * (ys - v[0]) - (xs - u[0]) * (v[1] - v[0])) / area
            b0 = 1.0 - b1 - b2
            tolerance = -1e-9
            inside = (b0 >= tolerance) & (b1 >= tolerance) & (b2 >= tolerance)
            if not inside.any():
                continue
            inverse = b0 / z[0] + b1 / z[1] + b2 / z[2]
            candidate = np.where(inside, 1.0 / np.maximum(inverse, 1e-300), np.inf)
            window = depth[y0:y1 + 1, x0:x1 + 1]
            np.minimum(window, candidate, out=window)
    return depth


def through_gap(label_depth: np.ndarray, gap_depth: np.ndarray, *, tolerance: float = 0.01) -> np.ndarray:
    """Pixels whose label (depth > 0) lies more than ``tolerance`` (relative) behind the gap
    mesh on the same ray: the ray crossed a gap before hitting the labelled surface."""
    label_depth = np.asarray(label_depth, np.float64)
    return (label_depth > 0) & (gap_depth < label_depth * (1.0 - tolerance))
