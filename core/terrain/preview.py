"""Quick looks at a terrain without Blender: a shaded relief map with sand, rocks and cameras.

Images are returned as arrays (north up, east right); writing them is the caller's job
(``cv2.imwrite`` expects BGR, so reverse the last axis).
"""
from __future__ import annotations

import numpy as np

from .heightfield import Terrain


def hillshade(terrain: Terrain, sun_direction: tuple[float, float, float]) -> np.ndarray:
    """Lambertian shading [R, R] in [0, 1] of the bare ground lit from ``sun_direction`` (unit, toward the sun)."""
    d_x, d_y = terrain.gradient()
    normals = np.stack([-d_x, -d_y, np.ones_like(d_x)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return np.clip(normals @ np.asarray(sun_direction, dtype=np.float64), 0.0, 1.0)


def overview_image(terrain: Terrain, sun_direction: tuple[float, float, float], cameras=(),
                   *, marker_px: int = 2) -> np.ndarray:
    """RGB uint8 map [R, R, 3], north (+y) up: shaded relief, sand tinted, rocks dark, cameras red.

    A camera's central-ray ground target is drawn green and joined to it by a thin line of
    samples, so the rig's layout and aim can be checked at a glance.
    """
    shade = hillshade(terrain, sun_direction)
    sand = terrain.sand_mask.astype(np.float64)
    bedrock_colour = np.array([0.55, 0.45, 0.38])
    sand_colour = np.array([0.80, 0.55, 0.40])
    colour = (1 - sand)[..., None] * bedrock_colour + sand[..., None] * sand_colour
    image = (0.25 + 0.75 * shade)[..., None] * colour
    resolution = terrain.resolution

    def to_pixel(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        col = np.round((np.asarray(x) + terrain.extent_m / 2) / terrain.cell_m).astype(np.int64)
        row = np.round((np.asarray(y) + terrain.extent_m / 2) / terrain.cell_m).astype(np.int64)
        return row, col

    def stamp(rows: np.ndarray, cols: np.ndarray, value: np.ndarray, radius: int) -> None:
        for d_row in range(-radius, radius + 1):
            for d_col in range(-radius, radius + 1):
                r, c = rows + d_row, cols + d_col
                keep = (r >= 0) & (r < resolution) & (c >= 0) & (c < resolution)
                image[r[keep], c[keep]] = value

    if len(terrain.rocks):
        rows, cols = to_pixel(terrain.rocks[:, 0], terrain.rocks[:, 1])
        stamp(rows, cols, np.array([0.15, 0.13, 0.12]), 0)
    for pose in cameras:
        centre = pose.camera_center
        if np.isfinite(pose.target).all():
            t = np.linspace(0.0, 1.0, 64)
            line = centre[None, :2] + t[:, None] * (pose.target[None, :2] - centre[None, :2])
            rows, cols = to_pixel(line[:, 0], line[:, 1])
            stamp(rows, cols, np.array([0.2, 0.8, 0.2]), 0)
            rows, cols = to_pixel(pose.target[None, 0], pose.target[None, 1])
            stamp(rows, cols, np.array([0.1, 1.0, 0.1]), marker_px)
        rows, cols = to_pixel(centre[None, 0], centre[None, 1])
        stamp(rows, cols, np.array([1.0, 0.1, 0.1]), marker_px)
    # Row 0 is the southern edge: flip so north is up.
    return (np.clip(image[::-1], 0.0, 1.0) * 255).astype(np.uint8)
