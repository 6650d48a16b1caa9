"""Relative depth priors pinned to the scene's scale by the SfM points each image observes."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from esgs.core.priors.align import align_depth_to_points, project_points

WIDTH, HEIGHT = 40, 30
K = torch.tensor([[35.0, 0.0, 20.0], [0.0, 35.0, 15.0], [0.0, 0.0, 1.0]])


def _view(seed=0):
    """A camera looking down +z at a tilted plane: its true depth map and the pose."""
    rng = np.random.default_rng(seed)
    angle = 0.3
    rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    translation = np.array([0.2, -0.1, 0.5])
    viewmat = np.eye(4)
    viewmat[:3, :3], viewmat[:3, 3] = rotation, translation
    columns, rows = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    depth = 4.0 + 0.05 * columns + 0.08 * rows  # any smooth positive field will do
    return depth, torch.tensor(viewmat, dtype=torch.float32), rng, rotation, translation


def _points_on(depth, rotation, translation, rng, count):
    """World points that project to random pixel centres at the view's true depth."""
    columns = rng.integers(0, WIDTH, count)
    rows = rng.integers(0, HEIGHT, count)
    z = depth[rows, columns]
    camera = np.stack([(columns + 0.5 - 20.0) / 35.0 * z, (rows + 0.5 - 15.0) / 35.0 * z, z], axis=1)
    return (camera - translation) @ rotation  # inverse of x_cam = R x_world + t


def test_projection_matches_the_pinhole_model():
    depth, viewmat, rng, rotation, translation = _view()
    points = _points_on(depth, rotation, translation, rng, 50)
    pixels, z = project_points(points, K, viewmat)
    assert np.all(np.abs(pixels - np.floor(pixels) - 0.5) < 1e-4)  # back at the pixel centres
    np.testing.assert_allclose(z, depth[np.floor(pixels[:, 1]).astype(int), np.floor(pixels[:, 0]).astype(int)],
                               rtol=1e-5)


def test_recovers_a_known_scale_and_shift_despite_outliers():
    depth, viewmat, rng, rotation, translation = _view()
    relative = torch.tensor((depth - 3.0) / 2.5, dtype=torch.float32)  # affine in depth, as NDN's output
    points = _points_on(depth, rotation, translation, rng, 300)
    wrong = rng.choice(300, 30, replace=False)
    points[wrong] *= rng.uniform(0.3, 0.7, (30, 1))  # 10 % badly triangulated points
    valid = torch.ones(HEIGHT, WIDTH, dtype=torch.bool)
    valid[:5] = False  # e.g. sky: neither fitted nor returned
    result = align_depth_to_points(relative, valid, K, viewmat, points)
    assert result.depth is not None and result.reason == ""
    assert result.scale == pytest.approx(2.5, rel=2e-3) and result.shift == pytest.approx(3.0, abs=1e-2)
    aligned = result.depth.numpy()
    assert np.all(aligned[:5] == 0)
    np.testing.assert_allclose(aligned[5:], depth[5:], rtol=3e-3)
    assert result.median_error < 1e-3 and 200 < result.points <= 300


def test_refuses_fits_it_cannot_trust():
    depth, viewmat, rng, rotation, translation = _view()
    valid = torch.ones(HEIGHT, WIDTH, dtype=torch.bool)
    relative = torch.tensor(depth, dtype=torch.float32)
    few = align_depth_to_points(relative, valid, K, viewmat, _points_on(depth, rotation, translation, rng, 5))
    assert few.depth is None and "need 20" in few.reason and not few.contradicts  # no evidence either way
    none = align_depth_to_points(relative, valid, K, viewmat, np.zeros((0, 3)))
    assert none.depth is None and "no SfM points" in none.reason and not none.contradicts
    points = _points_on(depth, rotation, translation, rng, 100)
    inverted = align_depth_to_points(torch.tensor(10.0 - depth, dtype=torch.float32), valid, K, viewmat, points)
    assert inverted.depth is None and "not positive" in inverted.reason and inverted.contradicts
    behind = points.copy()
    camera = behind @ rotation.T + translation
    behind = (camera * np.array([1, 1, -1]) - translation) @ rotation  # mirrored behind the camera
    assert align_depth_to_points(relative, valid, K, viewmat, behind).points == 0
