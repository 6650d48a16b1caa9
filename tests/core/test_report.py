"""Report pictures: colour maps, crops and curves carry the data they are given."""
from __future__ import annotations

import json

import numpy as np
import pytest

from esgs.core.apps import report
from esgs.core.apps.demo import DemoConfig
from esgs.core.errors import ConfigError


def test_colorize_depth_orders_near_to_far_and_blanks_invalid():
    depth = np.tile(np.linspace(1.0, 10.0, 64, dtype=np.float32), (8, 1))
    depth[:, :4] = 0.0
    image = report.colorize_depth(depth)
    assert image.shape == (8, 64, 3) and image.dtype == np.uint8
    assert np.all(image[:, :4] == 0)
    # turbo: near (small depth) is red-ish, far is blue-ish
    near, far = image[0, 8].astype(int), image[0, -1].astype(int)
    assert near[0] > near[2] and far[2] > far[0]


def test_colorize_normals_maps_axes_to_channels():
    normals = np.zeros((2, 2, 3), np.float32)
    normals[0, 0] = (1, 0, 0)
    normals[0, 1] = (0, 0, -1)
    image = report.colorize_normals(normals)
    assert tuple(image[0, 0]) == (255, 127, 127)
    assert tuple(image[0, 1]) == (127, 127, 0)
    assert np.all(image[1] == 0)  # zero-length normals are invalid


def test_magnified_crop_repeats_pixels():
    image = np.arange(16 * 16 * 3, dtype=np.uint8).reshape(16, 16, 3)
    crop = report.magnified_crop(image, (2, 3, 4, 5), scale=3)
    assert crop.shape == (15, 12, 3)
    assert np.array_equal(crop[::3, ::3], image[3:8, 2:6])


def test_curves_are_read_from_events_and_drawn(tmp_path):
    events = tmp_path / "events.jsonl"
    lines = [json.dumps({"step": s, "total": 100, "stage": "train", "kind": "progress",
                         "metrics": {"loss": 1.0 / s, "psnr": 10 + s / 10}}) for s in range(10, 101, 10)]
    lines.insert(3, "{half a line")
    lines.append(json.dumps({"step": 100, "total": 100, "stage": "train", "kind": "done", "metrics": {"psnr": 99}}))
    events.write_text("\n".join(lines))
    curves = report.read_curves(events)
    assert [s for s, _ in curves["psnr"]] == list(range(10, 101, 10))
    assert curves["loss"][0] == (10.0, 0.1)
    image = report.plot_curves({"a": curves["loss"]}, "loss", log_y=True)
    assert image.shape == (240, 480, 3)
    assert (image < 200).any(axis=2).sum() > 300  # the line and axes were drawn
    blank = report.plot_curves({"a": []}, "empty")
    assert blank.shape == (240, 480, 3)


def test_demo_config_is_checked():
    with pytest.raises(ConfigError, match="views"):
        DemoConfig(views=2).validate()
    with pytest.raises(ConfigError, match="iterations"):
        DemoConfig(iterations=5).validate()


def test_unseen_ground_is_tinted_and_outlined():
    image = np.full((20, 30, 3), 100, np.uint8)
    unseen = np.zeros((20, 30), bool)
    unseen[5:15, 10:20] = True
    marked = report.mark_unseen(image, unseen)
    assert marked.shape == (20, 30, 3)
    inner = marked[8:12, 13:17].reshape(-1, 3)
    # tinted towards magenta inside (red and blue up, green down), untouched outside, outlined at the edge
    assert np.all(inner[:, 0] > 100) and np.all(inner[:, 1] < 100) and np.all(inner[:, 2] > 100)
    np.testing.assert_array_equal(marked[0:3, 0:5], image[0:3, 0:5])
    np.testing.assert_array_equal(marked[5, 12], [255, 0, 255])
    np.testing.assert_array_equal(report.mark_unseen(image, np.zeros((20, 30), bool)), image)
    np.testing.assert_array_equal(report.mark_unseen(image, None), image)
