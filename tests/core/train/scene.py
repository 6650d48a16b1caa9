"""A tiny synthetic COLMAP scene for the training tests.

Known Gaussians tile a textured ground plane (z = 0); cameras on a ring look down at it.
Images are rendered with the reference rasterizer, the COLMAP model is PINHOLE and its
3D points are the Gaussian centres, jittered and with greyed colours, so training has
something to fix.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] world-to-camera (OpenCV axes) for a camera at ``eye`` looking at ``target``."""
    forward = np.asarray(target, float) - np.asarray(eye, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    view = np.eye(4)
    view[:3, :3] = rotation
    view[:3, 3] = -rotation @ np.asarray(eye, float)
    return view


def ground_truth_gaussians(grid: int = 14, seed: int = 0) -> dict[str, torch.Tensor]:
    """A grid x grid textured plane of flat Gaussians over [-1, 1]^2."""
    rng = np.random.default_rng(seed)
    u = np.linspace(-1.0, 1.0, grid)
    x, y = np.meshgrid(u, u, indexing="xy")
    means = np.stack([x.ravel(), y.ravel(), 0.02 * rng.standard_normal(grid * grid)], axis=1)
    colours = np.stack([0.5 + 0.4 * np.sin(3.0 * means[:, 0]), 0.5 + 0.4 * np.cos(2.0 * means[:, 1]),
                        0.5 + 0.3 * np.sign(np.sin(4.0 * means[:, 0]) * np.sin(4.0 * means[:, 1]))], axis=1)
    spacing = 2.0 / (grid - 1)
    count = grid * grid
    return {
        "means": torch.tensor(means, dtype=torch.float32),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]] * count),
        "scales": torch.tensor([[0.7 * spacing, 0.7 * spacing, 0.01]] * count, dtype=torch.float32),
        "opacities": torch.full((count,), 0.95),
        "colors": torch.tensor(np.clip(colours, 0.05, 0.95), dtype=torch.float32),
    }


def make_scene(root: Path, *, views: int = 10, width: int = 32, height: int = 24, grid: int = 14, points: int = 150,
               seed: int = 0, binary: bool = True, with_points: bool = True) -> Path:
    """Write a COLMAP scene folder (images/, sparse/0) under ``root`` and return it."""
    from esgs.core.colmap.geometry import matrix_to_quat_wxyz
    from esgs.core.colmap.io import write_model
    from esgs.core.colmap.model import Camera, ColmapModel, Image, Point3D
    from esgs.core.formats.imageio import write_png
    from esgs.core.render import rasterization

    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    truth = ground_truth_gaussians(grid, seed)
    focal = 0.5 * width / math.tan(math.radians(30.0))
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    camera = Camera(1, "PINHOLE", width, height, np.array([focal, focal, width / 2, height / 2]))
    images = {}
    for index in range(views):
        angle = 2 * math.pi * index / views
        eye = np.array([1.2 * math.cos(angle), 1.2 * math.sin(angle), 2.2])
        view = look_at(eye, np.array([0.1 * math.sin(angle), 0.0, 0.0]))
        render, _, _ = rasterization(truth["means"], truth["quats"], truth["scales"], truth["opacities"],
                                     truth["colors"], torch.tensor(view, dtype=torch.float32)[None],
                                     torch.tensor(K, dtype=torch.float32)[None], width, height,
                                     backend="reference")
        pixels = (render[0].clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
        name = f"view_{index:03d}.png"
        write_png(root / "images" / name, pixels)
        images[index + 1] = Image(index + 1, name, 1, matrix_to_quat_wxyz(view[:3, :3]), view[:3, 3].copy())
    model_points = {}
    if with_points:
        rng = np.random.default_rng(seed + 1)
        chosen = rng.choice(len(truth["means"]), size=min(points, len(truth["means"])), replace=False)
        for number, index in enumerate(chosen):
            xyz = truth["means"][index].numpy().astype(np.float64) + 0.03 * rng.standard_normal(3)
            rgb = (0.5 * truth["colors"][index].numpy() + 0.25) * 255
            model_points[number + 1] = Point3D(number + 1, xyz, rgb.astype(np.uint8), 0.5)
    model = ColmapModel({1: camera}, images, model_points)
    write_model(model, root / "sparse" / "0", binary=binary)
    return root
