"""Up-vector estimation for orient_up (esgs_addon/orient.py, plain numpy)."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.esgs_addon import orient
from tests.blender.colmap_helpers import look_at, tilt_rotation


def random_unit(rng, count):
    vectors = rng.normal(size=(count, 3))
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def test_rotation_between_maps_source_onto_target():
    rng = np.random.default_rng(0)
    sources, targets = random_unit(rng, 50), random_unit(rng, 50)
    pairs = list(zip(sources, targets)) + [(np.array([0, 0, 1.0]), np.array([0, 0, -1.0])),
                                            (np.array([1.0, 0, 0]), np.array([1.0, 0, 0]))]
    for source, target in pairs:
        rotation = orient.rotation_between(source, target)
        np.testing.assert_allclose(rotation @ source, target, atol=1e-12)
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)


def test_plane_fit_ignores_outliers():
    rng = np.random.default_rng(1)
    tilt = tilt_rotation()
    plane = np.column_stack([rng.uniform(-5, 5, (400, 2)), 0.02 * rng.normal(size=400)])
    outliers = np.column_stack([rng.uniform(-5, 5, (100, 2)), rng.uniform(0.5, 4.0, 100)])  # rocks, a building
    points = np.vstack([plane, outliers]) @ tilt.T + np.array([3.0, -2.0, 7.0])
    normal, centroid, flatness = orient.fit_plane(points)
    expected = tilt @ np.array([0, 0, 1.0])
    angle = np.degrees(np.arccos(min(1.0, abs(normal @ expected))))
    assert angle < 1.0
    assert abs((centroid - np.array([3.0, -2.0, 7.0])) @ expected) < 0.05
    assert flatness < 0.1


def cameras_around(tilt: np.ndarray, count: int = 6) -> np.ndarray:
    poses = []
    for index in range(count):
        angle = 2 * np.pi * index / count
        centre = tilt @ np.array([8 * np.cos(angle), 8 * np.sin(angle), 4.0])
        poses.append(look_at(centre, np.zeros(3), down_hint=tilt @ np.array([0, 0, -1.0])))
    return np.stack(poses)


def test_up_comes_from_the_ground_plane_with_the_cameras_sign():
    rng = np.random.default_rng(2)
    tilt = tilt_rotation()
    poses = cameras_around(tilt)
    ground = np.column_stack([rng.uniform(-5, 5, (300, 2)), 0.02 * rng.normal(size=300)]) @ tilt.T
    up = orient.estimate_up(poses, ground)
    np.testing.assert_allclose(up, tilt @ np.array([0, 0, 1.0]), atol=2e-3)
    # the cameras alone point upwards too (they look down at the ground, so only roughly)
    camera_only = orient.estimate_up(poses, None)
    assert camera_only @ (tilt @ np.array([0, 0, 1.0])) > 0.5
    # no dominant plane (a blob of points): the cameras decide
    blob = rng.normal(size=(300, 3))
    np.testing.assert_allclose(orient.estimate_up(poses, blob), camera_only, atol=1e-12)


def test_alignment_transform_levels_the_ground_at_zero():
    rng = np.random.default_rng(3)
    tilt = tilt_rotation()
    offset = np.array([10.0, -4.0, 2.5])
    poses = cameras_around(tilt)
    ground = np.column_stack([rng.uniform(-5, 5, (300, 2)), 0.02 * rng.normal(size=300)]) @ tilt.T + offset
    poses[:, :3, 3] -= np.einsum("cij,j->ci", poses[:, :3, :3], offset)  # cameras move with the ground
    transform = orient.up_alignment_transform(poses, ground)
    np.testing.assert_allclose(transform[:3, :3] @ transform[:3, :3].T, np.eye(3), atol=1e-12)
    levelled = ground @ transform[:3, :3].T + transform[:3, 3]
    assert np.abs(levelled[:, 2]).max() < 0.1
    np.testing.assert_allclose(np.median(levelled, axis=0), 0.0, atol=1e-9)
    centres = -np.einsum("cji,cj->ci", poses[:, :3, :3], poses[:, :3, 3])
    levelled_centres = centres @ transform[:3, :3].T + transform[:3, 3]
    np.testing.assert_allclose(levelled_centres[:, 2], 4.0, atol=0.05)
