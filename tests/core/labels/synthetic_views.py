"""Tiny synthetic stereo views rendered in numpy: a textured height field seen by pinhole
cameras (exact depth known), for testing the CPU reconstruction without Blender."""
from __future__ import annotations

from pathlib import Path

import numpy as np

WIDTH, HEIGHT, FOCAL = 96, 64, 80.0


def height_at(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The surface: a flat plain with one 0.4 m Gaussian mound at (0.3, 2.5)."""
    return 0.4 * np.exp(-((x - 0.3) ** 2 + (y - 2.5) ** 2) / 0.5)


def texture_at(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Grey value 0-255: a sum of sinusoids of several wavelengths (texture at every scale)."""
    rng = np.random.default_rng(7)
    value = np.zeros_like(x)
    for wavelength in (0.08, 0.13, 0.21, 0.35, 0.6):
        for _ in range(3):
            angle, phase = rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi)
            value += np.sin(2 * np.pi * (x * np.cos(angle) + y * np.sin(angle)) / wavelength + phase)
    return np.clip(128 + 14 * value, 0, 255)


def camera(position: np.ndarray, yaw_deg: float, pitch_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(K [3, 3], world_to_camera [4, 4]) of a level camera (no roll) looking along yaw/pitch."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = rotation
    world_to_camera[:3, 3] = -rotation @ position
    K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1.0]])
    return K, world_to_camera


def render(K: np.ndarray, world_to_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(grey image [H, W] uint8, z-depth [H, W]) by ray marching the height field."""
    rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH] + 0.5
    rays_camera = np.stack([cols, rows, np.ones_like(cols)], -1) @ np.linalg.inv(K).T  # z = 1
    rotation = world_to_camera[:3, :3]
    origin = -rotation.T @ world_to_camera[:3, 3]
    rays = rays_camera @ rotation  # world directions with camera z = 1
    t_low = np.zeros(rays.shape[:2])
    t_high = np.full(rays.shape[:2], np.inf)
    above = lambda t: origin[2] + t * rays[..., 2] - height_at(origin[0] + t * rays[..., 0], origin[1] + t * rays[..., 1])
    for t in np.arange(0.05, 40.0, 0.02):
        hit = (above(np.full_like(t_low, t)) < 0) & ~np.isfinite(t_high)
        t_high[hit] = t
        t_low[~np.isfinite(t_high)] = t
    assert np.all(np.isfinite(t_high)), "every pixel must see the ground"
    for _ in range(30):  # bisection between the last point above and the first below
        middle = 0.5 * (t_low + t_high)
        below = above(middle) < 0
        t_high = np.where(below, middle, t_high)
        t_low = np.where(below, t_low, middle)
    hit_x, hit_y = origin[0] + t_high * rays[..., 0], origin[1] + t_high * rays[..., 1]
    return texture_at(hit_x, hit_y).astype(np.uint8), t_high  # camera z = 1 per unit t


def rover_poses(count: int = 5) -> list[tuple[np.ndarray, np.ndarray]]:
    """A short forward traverse with a sideways wander, mast 1.5 m high, looking 40 degrees down."""
    return [camera(np.array([0.12 * (i % 2), -0.6 + 0.3 * i, 1.5]), 90.0 + 4 * ((i % 3) - 1), -40.0)
            for i in range(count)]


def write_scene(folder: Path, count: int = 5) -> list[np.ndarray]:
    """A scene folder (images/, sparse/0 with surface points) of the traverse; returns the true depths."""
    from esgs.core.colmap import Camera, ColmapModel, Image, Point3D, write_model
    from esgs.core.colmap.geometry import matrix_to_quat_wxyz
    from esgs.core.formats.imageio import write_png

    rng = np.random.default_rng(3)
    x, y = rng.uniform(-1.5, 1.5, 300), rng.uniform(0.0, 6.0, 300)
    xyz = np.stack([x, y, height_at(x, y)], 1)
    points = {i + 1: Point3D(i + 1, xyz[i], np.array([128, 128, 128], np.uint8), 0.0, np.zeros(0, np.int64),
                             np.zeros(0, np.int64)) for i in range(len(xyz))}
    images, depths = {}, []
    for index, (K, world_to_camera) in enumerate(rover_poses(count), start=1):
        image, depth = render(K, world_to_camera)
        write_png(folder / "images" / f"v{index}.png", image)
        depths.append(depth)
        images[index] = Image(index, f"v{index}.png", 1, matrix_to_quat_wxyz(world_to_camera[:3, :3]),
                              world_to_camera[:3, 3].copy())
    cameras = {1: Camera(1, "PINHOLE", WIDTH, HEIGHT, np.array([FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2]))}
    write_model(ColmapModel(cameras, images, points), folder / "sparse" / "0")
    return depths
