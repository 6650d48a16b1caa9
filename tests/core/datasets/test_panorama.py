"""Panorama cutting: geometry of the views measured on the written files."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from esgs.core.colmap import read_model
from esgs.core.datasets import PanoramaOptions, equirectangular_directions, scene_from_panorama
from esgs.core.errors import ConfigError, DatasetError
from esgs.core.formats.imageio import read_image, write_png


def direction_colours(directions: np.ndarray) -> np.ndarray:
    """Colour = f(direction): each RGB channel is one world axis mapped to 0..255."""
    return 127.5 * (1.0 + directions)


def pixel_rays(camera, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """[N, 3] camera-frame rays through pixel positions (COLMAP pixel convention)."""
    fx, fy, cx, cy = camera.intrinsics()
    return np.stack([(xs - cx) / fx, (ys - cy) / fy, np.ones_like(xs)], axis=1)


@pytest.fixture(scope="module")
def colour_scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("colour")
    pano = np.clip(np.round(direction_colours(equirectangular_directions(1440, 720))), 0, 255).astype(np.uint8)
    write_png(folder / "pano.png", pano)
    options = PanoramaOptions(width=200, height=150, fov_deg=70.0, overlap=0.4, pitches_deg=(0.0, 35.0))
    report = scene_from_panorama(folder / "pano.png", folder / "scene", options)
    return folder / "scene", report, options


def test_views_show_the_colour_of_their_rays(colour_scene):
    scene, report, options = colour_scene
    model = read_model(scene / "sparse" / "0")
    assert len(model.images) == report["views_per_row"] * 2
    assert all(np.allclose(image.camera_center(), 0.0) for image in model.images.values())
    camera = model.cameras[1]
    ys, xs = np.mgrid[0 : camera.height, 0 : camera.width]
    rays = pixel_rays(camera, xs.ravel() + 0.5, ys.ravel() + 0.5)
    for image in model.images.values():
        world = rays @ image.rotation_matrix()  # R^T ray for every row
        world /= np.linalg.norm(world, axis=1, keepdims=True)
        expected = direction_colours(world)
        pixels = read_image(scene / "images" / image.name).reshape(-1, 3).astype(np.float64)
        # Bilinear resampling of a smooth field plus 8-bit rounding: about 1 DN.
        assert np.abs(pixels - expected).mean() < 1.5, image.name
        assert np.abs(pixels - expected).max() < 6.0, image.name


def test_overlap_and_field_of_view_match_the_request(colour_scene):
    scene, report, options = colour_scene
    model = read_model(scene / "sparse" / "0")
    camera = model.cameras[1]
    fx, _, cx, cy = camera.intrinsics()
    # Field of view from the rays through the left and right image edges of the centre row.
    left, right = pixel_rays(camera, np.array([0.0, camera.width]), np.array([cy, cy]))
    measured_fov = math.degrees(math.acos(left @ right / np.linalg.norm(left) / np.linalg.norm(right)))
    assert measured_fov == pytest.approx(options.fov_deg, abs=1e-6)
    row0 = sorted((image for image in model.images.values() if image.name.startswith("view_r00")), key=lambda i: i.name)
    xs = np.arange(camera.width) + 0.5
    for a, b in zip(row0, row0[1:] + row0[:1]):
        world = pixel_rays(camera, xs, np.full_like(xs, cy)) @ a.rotation_matrix()
        in_b = world @ b.rotation_matrix().T
        u = in_b[:, 0] / in_b[:, 2] * fx + cx
        inside = (in_b[:, 2] > 0) & (u >= 0) & (u <= camera.width)
        overlap = inside.mean()
        assert overlap >= options.overlap - 1.0 / camera.width
        assert overlap == pytest.approx(report["overlap"], abs=1.5 / camera.width)
    # The rows close the circle: the last view's neighbour is the first.
    assert report["views_per_row"] * report["yaw_step_deg"] == pytest.approx(360.0)
    saved = json.loads((scene / "panorama_report.json").read_text())
    assert saved["overlap"] == pytest.approx(report["overlap"])


def test_strip_is_cut_into_overlapping_crops(tmp_path):
    rng = np.random.default_rng(1)
    strip = rng.integers(0, 256, (200, 1000, 3), dtype=np.uint8)
    write_png(tmp_path / "strip.png", strip)
    report = scene_from_panorama(tmp_path / "strip.png", tmp_path / "scene", PanoramaOptions(width=320, height=180, overlap=0.5))
    assert report["kind"] == "strip" and not (tmp_path / "scene" / "sparse").exists()
    crops = sorted((tmp_path / "scene" / "images").iterdir())
    assert len(crops) == report["crops"] >= 2
    first, second = read_image(crops[0]), read_image(crops[1])
    assert first.shape == (180, 320, 3)
    shift = round((1.0 - report["overlap"]) * 320)
    assert report["overlap"] >= 0.5
    np.testing.assert_array_equal(first[:, shift:], second[:, : 320 - shift])
    # The crops together reach the right end of the strip.
    np.testing.assert_array_equal(read_image(crops[-1]), strip[-180:, -320:])


def test_bad_inputs_give_clear_errors_and_no_output(tmp_path):
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="cannot decode image"):
        scene_from_panorama(tmp_path / "broken.png", tmp_path / "scene")
    with pytest.raises(ConfigError, match="overlap"):
        scene_from_panorama(tmp_path / "broken.png", tmp_path / "scene", PanoramaOptions(overlap=0.99))
    assert not (tmp_path / "scene").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["broken.png"]
