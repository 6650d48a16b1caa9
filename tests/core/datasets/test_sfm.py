"""SfM datasets: failures are explained, a rendered synthetic scene is reconstructed."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from esgs.core.colmap import read_model
from esgs.core.datasets import SfmOptions, scene_from_images
from esgs.core.errors import DatasetError
from esgs.core.formats.imageio import write_png


def test_one_image_is_refused(tmp_path):
    write_png(tmp_path / "in" / "a.png", np.zeros((32, 32), np.uint8))
    with pytest.raises(DatasetError, match="at least 2 images, found 1"):
        scene_from_images(tmp_path / "in", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_unreadable_images_are_named(tmp_path):
    write_png(tmp_path / "in" / "a.png", np.zeros((32, 32), np.uint8))
    (tmp_path / "in" / "b.jpg").write_bytes(b"\xff\xd8 truncated")
    (tmp_path / "in" / "c.png").write_bytes(b"")
    with pytest.raises(DatasetError, match=r"2 of 3 images cannot be read: b\.jpg .*c\.png"):
        scene_from_images(tmp_path / "in", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_rotation_only_set_is_explained(panorama_views, tmp_path):
    with pytest.raises(DatasetError, match="rotation") as caught:
        scene_from_images(panorama_views / "images", tmp_path / "out", SfmOptions(single_camera=True))
    assert "esgs dataset rotation-only" in str(caught.value)
    assert not (tmp_path / "out").exists()
    assert [p.name for p in tmp_path.iterdir()] == []


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (scale, rotation [3, 3], translation [3]) that best maps source [N, 3] onto target [N, 3]."""
    mean_s, mean_t = source.mean(0), target.mean(0)
    s, t = source - mean_s, target - mean_t
    u, singular, vt = np.linalg.svd(t.T @ s / len(source))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ sign @ vt
    scale = np.trace(np.diag(singular) @ sign) / (s**2).sum(1).mean()
    return scale, rotation, mean_t - scale * rotation @ mean_s


@pytest.fixture(scope="module")
def rendered_scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rendered") / "scene"
    command = [sys.executable, "-m", "esgs.core", "scene", "--preset", "rocky_slope", "--views", "8",
               "--resolution", "320x180", "--samples", "8", "--out", str(folder)]
    subprocess.run(command, check=True, capture_output=True)
    return folder


@pytest.mark.slow
def test_rendered_scene_is_reconstructed(rendered_scene, tmp_path):
    truth = read_model(rendered_scene / "sparse" / "0")
    report = scene_from_images(rendered_scene / "images", tmp_path / "sfm", SfmOptions(single_camera=True))
    assert len(report["registered"]) >= 0.9 * len(truth.images)
    assert report["models"] == 1 and report["mean_reprojection_error_px"] < 1.0
    assert json.loads((tmp_path / "sfm" / "sfm_report.json").read_text())["registered"] == report["registered"]
    estimate = read_model(tmp_path / "sfm" / "sparse" / "0")
    assert {c.model for c in estimate.cameras.values()} == {"PINHOLE"}  # SIMPLE_RADIAL, undistorted
    assert estimate.cameras[1].params[0] == pytest.approx(truth.cameras[1].params[0], rel=0.01)  # self-calibrated focal
    true_by_name = {image.name: image for image in truth.images.values()}
    names = sorted(image.name for image in estimate.images.values())
    estimated = {image.name: image for image in estimate.images.values()}
    source = np.stack([estimated[n].camera_center() for n in names])
    target = np.stack([true_by_name[n].camera_center() for n in names])
    scale, rotation, translation = umeyama(source, target)
    aligned = scale * source @ rotation.T + translation
    spread = np.linalg.norm(target - target.mean(0), axis=1).mean()
    assert np.linalg.norm(aligned - target, axis=1).max() < 0.02 * spread
    for name in names:
        # world-to-camera rotations: R_true ~ R_est @ R_align^T
        difference = true_by_name[name].rotation_matrix() @ (estimated[name].rotation_matrix() @ rotation.T).T
        angle = np.degrees(np.arccos(np.clip((np.trace(difference) - 1) / 2, -1, 1)))
        assert angle < 0.5, name
    for name in names:
        assert (tmp_path / "sfm" / "images" / name).is_file()


def test_a_second_model_of_images_already_registered_is_dropped_and_separate_groups_are_refused(tmp_path):
    from esgs.core.datasets.sfm import choose_model
    from esgs.core.errors import DatasetError

    main = [f"view_{i:03d}.png" for i in range(14)]
    # incremental mapping restarted from leftover pairs: 2 images the main model holds already
    assert choose_model({0: ["view_003.png", "view_004.png"], 1: main}, tmp_path) == 1
    with pytest.raises(DatasetError, match="2 disconnected models: 14 images") as error:
        choose_model({0: main, 1: ["view_020.png", "view_021.png", "view_003.png"]}, tmp_path)
    assert str(tmp_path) in str(error.value)
