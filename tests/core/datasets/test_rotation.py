"""Rotation-only station estimate: synthetic views with known rotations, and the real Navcam frames."""
from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from esgs.core.colmap import read_model
from esgs.core.datasets import RotationOnlyOptions, scene_from_rotation_only
from esgs.core.errors import DatasetError
from tests.conftest import require_shared


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cosine = (np.trace(a @ b.T) - 1.0) / 2.0
    return math.degrees(math.acos(np.clip(cosine, -1.0, 1.0)))


def test_rotations_and_focal_are_recovered(panorama_views, tmp_path):
    truth = read_model(panorama_views / "sparse" / "0")
    true_focal = truth.cameras[1].params[0]
    report = scene_from_rotation_only(
        panorama_views / "images", tmp_path / "station", RotationOnlyOptions(focal_px=1.06 * true_focal, max_features=1500)
    )
    assert report["unregistered"] == [] and len(report["registered"]) == len(truth.images)
    assert report["focal_px"] == pytest.approx(true_focal, rel=3e-3)
    assert report["mean_error_px"] < 0.5
    estimate = read_model(tmp_path / "station" / "sparse" / "0")
    by_name = {image.name: image for image in truth.images.values()}
    estimated = {image.name: image for image in estimate.images.values()}
    # Both models share a world frame only up to one rotation: compare relative rotations to the first view.
    names = sorted(by_name)
    reference_true, reference_estimate = by_name[names[0]].rotation_matrix(), estimated[names[0]].rotation_matrix()
    for name in names[1:]:
        relative_true = by_name[name].rotation_matrix() @ reference_true.T
        relative_estimate = estimated[name].rotation_matrix() @ reference_estimate.T
        assert rotation_angle_deg(relative_true, relative_estimate) < 0.1, name
    assert all(np.allclose(image.camera_center(), 0.0) for image in estimate.images.values())
    assert json.loads((tmp_path / "station" / "rotation_report.json").read_text())["focal_px"] == pytest.approx(report["focal_px"])


def test_frames_that_do_not_overlap_are_refused(tmp_path):
    from esgs.core.formats.imageio import write_png

    rng = np.random.default_rng(3)
    for k in range(2):
        write_png(tmp_path / "in" / f"{k}.png", rng.integers(0, 256, (120, 160), dtype=np.uint8))
    with pytest.raises(DatasetError, match="no two frames share enough matched features"):
        scene_from_rotation_only(tmp_path / "in", tmp_path / "out")
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
@pytest.mark.shared_data
def test_navcam_station_mosaic_error_is_below_one_pixel(tmp_path):
    root = require_shared("mars_navcam_pan")
    with open(root / "frames.csv", newline="") as handle:
        names = [row["file"] for row in csv.DictReader(handle) if row["site"] == "96" and row["drive"] == "2724"]
    assert len(names) == 31
    report = scene_from_rotation_only(root / "images", tmp_path / "navcam", RotationOnlyOptions(focal_px=615.0, max_features=1500), names=names)
    assert len(report["registered"]) == 31
    assert report["mean_error_px"] < 1.0 and report["median_error_px"] < 1.0
    # The README's rough focal length from the 45 degree field of view: 610-620 px.
    assert 600.0 < report["focal_px"] < 640.0
    assert report["kept_fraction"] > 0.4


@pytest.mark.parametrize("refine_principal_point", [False, True])
def test_adjustment_jacobian_matches_finite_differences(refine_principal_point):
    from scipy.spatial.transform import Rotation

    from esgs.core.datasets.rotation import _station_residuals

    rng = np.random.default_rng(0)
    rotations = {k: Rotation.from_rotvec(rng.normal(scale=0.4, size=3)).as_matrix() for k in range(3)}
    free = [1, 2]
    first, second = np.array([0, 0, 1, 1, 2]), np.array([1, 2, 2, 0, 0])
    flat = (first, second, rng.uniform(50, 250, (5, 2)), rng.uniform(50, 250, (5, 2)))
    intrinsics = (300.0, 150.0, 140.0)
    residuals, jacobian = _station_residuals(rotations, free, flat, intrinsics, True, refine_principal_point, True)
    step = 1e-6
    for column in range(jacobian.shape[-1]):
        delta = np.zeros(jacobian.shape[-1])
        delta[column] = step
        moved = dict(rotations)
        for position, image in enumerate(free):
            moved[image] = Rotation.from_rotvec(delta[3 * position : 3 * position + 3]).as_matrix() @ rotations[image]
        focal, cx, cy = intrinsics
        focal += delta[6]
        if refine_principal_point:
            cx, cy = cx + delta[7], cy + delta[8]
        shifted, _ = _station_residuals(moved, free, flat, (focal, cx, cy), True, refine_principal_point, False)
        numeric = (shifted - residuals) / step
        np.testing.assert_allclose(jacobian[:, :, column], numeric, rtol=1e-4, atol=1e-4)
