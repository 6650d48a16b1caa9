"""Lifting depth-prior pixels into the scene and drawing which pixels to lift."""
from __future__ import annotations

import numpy as np

from esgs.core.priors.seeding import lift_pixels, sample_prior_pixels
from tests.core.train.scene import look_at


def test_lifted_pixels_project_back_to_their_pixel_centres_at_their_depth():
    rng = np.random.default_rng(0)
    K = np.array([[40.0, 0.0, 17.5], [0.0, 38.0, 11.0], [0.0, 0.0, 1.0]])
    world_to_camera = look_at(np.array([0.3, -2.0, 1.5]), np.zeros(3))
    depth = rng.uniform(1.0, 5.0, (24, 32))
    rows, cols = np.meshgrid(np.arange(24), np.arange(32), indexing="ij")
    points = lift_pixels(depth, rows.ravel(), cols.ravel(), K, world_to_camera)
    camera = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    np.testing.assert_allclose(camera[:, 2], depth.ravel(), rtol=1e-12)
    pixels = camera @ K.T
    np.testing.assert_allclose(pixels[:, 0] / pixels[:, 2], cols.ravel() + 0.5, atol=1e-9)
    np.testing.assert_allclose(pixels[:, 1] / pixels[:, 2], rows.ravel() + 0.5, atol=1e-9)


def test_drawn_pixels_are_distinct_valid_and_never_of_zero_weight():
    valid = np.zeros((10, 12), dtype=bool)
    valid[2:8, 3:9] = True
    weights = np.ones((10, 12))
    weights[2:8, 3:5] = 0.0  # valid but never to be drawn
    rows, cols = sample_prior_pixels(valid, 20, np.random.default_rng(1), weights)
    assert len(rows) == 20
    assert len(set(zip(rows.tolist(), cols.tolist()))) == 20
    assert valid[rows, cols].all()
    assert (weights[rows, cols] > 0).all()
    # fewer candidates than asked: every one of them, once
    rows, cols = sample_prior_pixels(valid, 1000, np.random.default_rng(1), weights)
    assert len(rows) == int((valid & (weights > 0)).sum())


def test_weights_steer_the_draw_and_the_same_generator_draws_the_same_pixels():
    valid = np.ones((20, 20), dtype=bool)
    weights = np.full((20, 20), 0.01)
    weights[:, 10:] = 1.0
    rows, cols = sample_prior_pixels(valid, 50, np.random.default_rng(2), weights)
    assert (cols >= 10).mean() > 0.8
    again = sample_prior_pixels(valid, 50, np.random.default_rng(2), weights)
    np.testing.assert_array_equal(rows, again[0])
    np.testing.assert_array_equal(cols, again[1])


def test_nothing_to_draw_gives_empty_arrays():
    rows, cols = sample_prior_pixels(np.zeros((4, 4), dtype=bool), 5, np.random.default_rng(0))
    assert rows.size == cols.size == 0
    rows, cols = sample_prior_pixels(np.ones((4, 4), dtype=bool), 0, np.random.default_rng(0))
    assert rows.size == 0
