"""Tiny NDN models and scene folders for fast tests."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from esgs.core.ndn.config import NDNConfig, NDNDiffusionConfig, NDNModelConfig


def tiny_config(prediction: str = "epsilon") -> NDNConfig:
    """A ~40k-parameter model at 32 px with a short schedule (fast on a CPU)."""
    return NDNConfig(model=NDNModelConfig(base_channels=8, levels=2, time_dim=16, working_size=32),
                     diffusion=NDNDiffusionConfig(timesteps=50, sample_steps=3, prediction=prediction))


def make_scene(root: Path, views: int = 4, width: int = 48, height: int = 27, seed: int = 0,
               with_gt: bool = True, panorama: bool = False) -> Path:
    """A scene folder: textured images, a COLMAP model of cameras on a line looking at a
    tilted plane, and (optionally) exact plane depth/normals as ``priors/gt``. With
    ``panorama`` the cameras instead share one centre and turn 5 degrees apart (the gt maps
    are then only placeholders)."""
    from esgs.core.colmap.geometry import matrix_to_quat_wxyz
    from esgs.core.colmap.io import write_model
    from esgs.core.colmap.model import Camera, ColmapModel, Image, Point3D
    from esgs.core.formats.imageio import write_png
    from esgs.core.priors import write_prior_maps

    rng = np.random.default_rng(seed)
    focal = 40.0
    camera = Camera(1, "PINHOLE", width, height, np.array([focal, focal, width / 2, height / 2]))
    images = {}
    # plane in camera coordinates: n . X = d with n tilted toward the camera
    plane_normal = np.array([0.0, -0.6, -0.8])
    plane_offset = -4.0
    v, u = np.mgrid[0:height, 0:width] + 0.5
    rays = np.stack([(u - width / 2) / focal, (v - height / 2) / focal, np.ones_like(u)], axis=-1)
    depth = plane_offset / (rays @ plane_normal)  # z depth of the plane along each ray
    for index in range(views):
        name = f"view_{index:03d}.png"
        translation = np.array([-0.3 * index, 0.0, 0.0])
        rotation = np.eye(3)
        if panorama:
            angle = np.radians(5.0 * index)
            rotation = np.array([[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]])
            translation = np.zeros(3)
        images[index + 1] = Image(index + 1, name, 1, matrix_to_quat_wxyz(rotation), translation)
        (root / "images").mkdir(parents=True, exist_ok=True)
        texture = (rng.uniform(0, 255, (height, width, 3))).astype(np.uint8)
        write_png(root / "images" / name, texture)
        if with_gt:
            mask = np.ones((height, width), bool)
            mask[:2] = False  # a strip of "sky"
            normal = np.broadcast_to(plane_normal, (height, width, 3)).astype(np.float32)
            write_prior_maps(root, "gt", name, depth=np.where(mask, depth, 0).astype(np.float32), normal=normal,
                             mask=mask)
    points = {1: Point3D(1, np.array([0.0, 0.0, 4.0]), np.array([128, 128, 128], np.uint8), 0.5)}
    write_model(ColmapModel({1: camera}, images, points), root / "sparse" / "0")
    return root


@pytest.fixture
def scene(tmp_path: Path) -> Path:
    return make_scene(tmp_path / "scene")


def perturbed_weights(path, config, scale: float):
    """A checkpoint at ``path`` of a freshly built model whose weights are nudged by seeded noise
    (``scale`` x N(0, 1)), so its outputs are not the zero-initialised ones."""
    import torch

    from esgs.core.ndn.train import build_model, save_checkpoint

    torch.manual_seed(0)
    model, _ = build_model(config)
    for parameter in model.parameters():
        parameter.data.add_(scale * torch.randn_like(parameter))
    return save_checkpoint(path, model, config)
