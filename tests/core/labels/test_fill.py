"""Hole filling of label renders: what is filled, how well, and that it is flagged."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.errors import ConfigError
from esgs.core.labels.fill import EMPTY, FILLED, RENDERED, FillOptions, fill_missing, fill_region, membrane_fill


def plane_view(height: int = 60, width: int = 80) -> tuple[np.ndarray, np.ndarray]:
    """Depth [H, W] of a slanted plane (inverse depth linear in the pixel) and its normal."""
    rows, cols = np.mgrid[0:height, 0:width] + 0.5
    depth = 1.0 / (0.1 + 0.002 * cols + 0.003 * rows)
    normal = np.zeros((height, width, 3), np.float32)
    normal[...] = np.array([0.2, -0.9, -0.3]) / np.linalg.norm([0.2, -0.9, -0.3])
    return depth.astype(np.float32), normal


def test_enclosed_hole_in_a_plane_is_filled_exactly_and_flagged():
    depth, normal = plane_view()
    valid = np.ones(depth.shape, bool)
    valid[20:30, 30:42] = False
    filled_depth, filled_normal, mask = fill_missing(np.where(valid, depth, 0), np.where(valid[..., None], normal, 0),
                                                     valid, FillOptions(edge_radius_px=0))
    hole = ~valid
    assert np.all(mask[hole] == FILLED) and np.all(mask[valid] == RENDERED)
    np.testing.assert_allclose(filled_depth[hole], depth[hole], rtol=1e-5)
    np.testing.assert_allclose(filled_normal[hole], normal[hole], atol=1e-5)
    np.testing.assert_array_equal(filled_depth[valid], depth[valid])  # rendered pixels untouched


def test_sky_touching_the_border_stays_empty_and_does_not_pull_the_fill():
    depth, normal = plane_view()
    valid = np.ones(depth.shape, bool)
    valid[:12, :] = False  # sky band along the top border
    valid[13:20, 30:40] = False  # a hole one row below the sky: closed off by a single rendered row
    options = FillOptions(edge_radius_px=0)
    filled_depth, _, mask = fill_missing(np.where(valid, depth, 0), np.where(valid[..., None], normal, 0), valid, options)
    assert np.all(mask[:12] == EMPTY) and np.all(filled_depth[:12] == 0)
    assert np.all(mask[13:20, 30:40] == FILLED)
    # the free boundary towards the sky is not a zero-depth boundary: fill stays close to the plane
    np.testing.assert_allclose(filled_depth[13:20, 30:40], depth[13:20, 30:40], rtol=0.02)


def test_large_holes_stay_empty_and_edge_band_is_filled():
    depth, normal = plane_view()
    valid = np.ones(depth.shape, bool)
    valid[10:50, 10:70] = False  # half the image: not a hole to invent
    region = fill_region(valid, FillOptions(max_hole_fraction=0.05, edge_radius_px=0))
    assert not region.any()
    region = fill_region(valid, FillOptions(max_hole_fraction=0.05, edge_radius_px=2))
    assert region[10, 30] and region[11, 30] and not region[13, 30] and not region[30, 40]
    assert not region[valid].any()


def test_membrane_fill_reproduces_linear_functions():
    rows, cols = np.mgrid[0:30, 0:40]
    values = np.stack([2.0 * rows - cols + 3, 0.5 * cols], axis=-1)
    known = np.ones((30, 40), bool)
    known[5:25, 5:35] = False
    result = membrane_fill(np.where(known[..., None], values, 0.0), known, ~known)
    np.testing.assert_allclose(result, values, atol=1e-8)


def test_nothing_rendered_or_nothing_missing():
    depth, normal = plane_view(10, 12)
    none = np.zeros(depth.shape, bool)
    filled_depth, _, mask = fill_missing(np.zeros_like(depth), np.zeros_like(normal), none)
    assert np.all(mask == EMPTY) and np.all(filled_depth == 0)
    _, _, mask = fill_missing(depth, normal, ~none)
    assert np.all(mask == RENDERED)


def test_bad_options_are_config_errors():
    with pytest.raises(ConfigError, match="max_hole_fraction"):
        FillOptions(max_hole_fraction=2.0).validate()
    with pytest.raises(ConfigError, match="edge_radius_px"):
        FillOptions(edge_radius_px=-1).validate()
