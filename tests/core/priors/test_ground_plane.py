"""The near-ground plane of a view (``priors.ground_plane``) and its use as the shape of the
labels' holes in ``priors/auto``: a rover-height view of flat ground with a hole at its bottom
edge, where the network's shape is wrong."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.priors.auto import AutoPriorSettings, fuse_view
from esgs.core.priors.ground_plane import fit_view_plane, plane_depth
from esgs.core.priors.io import PriorMaps

H, W = 60, 90
K = np.array([[80.0, 0.0, 45.0], [0.0, 80.0, 20.0], [0.0, 0.0, 1.0]])  # principal point high: mostly ground
CAMERA_HEIGHT = 1.5
PITCH_DEG = 12.0  # looking down


def _ground_depth() -> np.ndarray:
    """z-depth of flat ground 1.5 m under a camera pitched down by 12 degrees (0 above the horizon)."""
    pitch = np.radians(PITCH_DEG)
    # camera y points down; the ground normal (pointing down, away from the camera) in the camera frame
    normal = np.array([0.0, np.cos(pitch), np.sin(pitch)])
    rows, columns = np.mgrid[0:H, 0:W]
    rays = np.stack([(columns + 0.5 - K[0, 2]) / K[0, 0], (rows + 0.5 - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    facing = rays @ normal
    return np.where(facing > 1e-6, CAMERA_HEIGHT / np.maximum(facing, 1e-6), 0.0).astype(np.float32)


def test_the_fitted_plane_gives_the_ground_back_and_says_where_it_is_steep():
    truth = _ground_depth()
    labelled = (truth > 0) & (truth < 40)
    rng = np.random.default_rng(1)
    noisy = truth * (1 + 0.003 * rng.standard_normal(truth.shape)).astype(np.float32)
    outliers = rng.random(truth.shape) < 0.1  # a rock field's worth of pixels off the plane
    noisy[outliers] *= 0.6
    plane = fit_view_plane(noisy, labelled, K)
    assert plane is not None
    assert plane.offset == pytest.approx(CAMERA_HEIGHT, rel=0.01)
    assert plane.inlier_share > 0.85
    depth, angle = plane_depth(plane, K, H, W)
    ground = truth > 0
    np.testing.assert_allclose(depth[ground], truth[ground], rtol=0.02)
    assert (depth[~ground] == 0).all()  # rays above the horizon never meet it in front of the camera
    assert angle[-1].min() > angle[ground].min()  # the bottom row meets the ground most steeply
    assert fit_view_plane(noisy, np.zeros_like(labelled), K) is None  # nothing to fit


def test_a_hole_in_the_near_ground_is_filled_by_the_plane_where_the_rays_are_steep():
    truth = _ground_depth()
    ground = truth > 0
    hole = np.zeros((H, W), bool)
    hole[-12:, :] = True  # the ground right under the camera: seen by one view, no stereo
    labels = PriorMaps(depth=np.where(hole | ~ground, 0.0, truth).astype(np.float32), normal=None,
                       mask=ground & ~hole)
    # a network whose shape is wrong there: its depth keeps growing towards the bottom edge
    rows = np.arange(H, dtype=np.float32)[:, None] * np.ones((1, W), np.float32)
    wrong = np.where(hole, truth * (1 + 0.04 * (rows - (H - 12))), truth).astype(np.float32)
    ndn = PriorMaps(depth=np.where(ground, wrong, 0.0).astype(np.float32), normal=None, mask=ground)
    sfm = np.zeros_like(truth)
    sfm[:-12:4, ::4] = truth[:-12:4, ::4]
    sky = ~ground
    without = fuse_view(sfm, labels, ndn, sky, AutoPriorSettings(ground_guide_angle=0), intrinsics=K)
    guided = fuse_view(sfm, labels, ndn, sky, AutoPriorSettings(), intrinsics=K)
    error_without = np.abs(without.depth[hole] / truth[hole] - 1)
    error_guided = np.abs(guided.depth[hole] / truth[hole] - 1)
    assert error_without.max() > 0.15  # the network's shape carried into the hole
    assert error_guided.max() < 0.02  # the plane's shape instead
    assert guided.report["ground_guide"]["share"] == pytest.approx(1.0)
    np.testing.assert_array_equal(guided.depth[~hole], without.depth[~hole])  # labels untouched
    # no intrinsics: the plane cannot be drawn and the network's shape is used, as before
    plain = fuse_view(sfm, labels, ndn, sky, AutoPriorSettings(), intrinsics=None)
    np.testing.assert_array_equal(plain.depth, without.depth)
    # a gate steeper than any ray in the hole: the network again
    steep = fuse_view(sfm, labels, ndn, sky, AutoPriorSettings(ground_guide_angle=89), intrinsics=K)
    np.testing.assert_array_equal(steep.depth, without.depth)


def test_the_gate_is_validated():
    from esgs.core.errors import ConfigError

    with pytest.raises(ConfigError, match="ground_guide_angle"):
        AutoPriorSettings(ground_guide_angle=95).validate()


def test_a_view_from_above_keeps_the_networks_shape_in_its_holes():
    """A nadir view 10 m over flat ground: its rays meet the plane steeply everywhere, but the
    camera is as high over it as the ground is far, so the holes are patches amid the labels
    and keep NDN's shape (the plane would flatten relief the network sees)."""
    truth = np.full((H, W), 10.0, np.float32)
    hole = np.zeros((H, W), bool)
    hole[20:35, 30:60] = True
    labels = PriorMaps(depth=np.where(hole, 0.0, truth).astype(np.float32), normal=None, mask=~hole)
    bump = truth * (1 + 0.1 * hole)  # the network sees a mound in the hole
    ndn = PriorMaps(depth=bump.astype(np.float32), normal=None, mask=np.ones((H, W), bool))
    sfm = np.zeros_like(truth)
    sfm[::4, ::4] = np.where(hole, 0.0, truth)[::4, ::4]
    guided = fuse_view(sfm, labels, ndn, None, AutoPriorSettings(), intrinsics=K)
    without = fuse_view(sfm, labels, ndn, None, AutoPriorSettings(ground_guide_angle=0), intrinsics=K)
    assert guided.report["ground_guide"]["share"] == 0.0
    assert guided.report["ground_guide"]["height_share"] == pytest.approx(1.0, rel=0.02)
    np.testing.assert_array_equal(guided.depth, without.depth)
    # the same view counted as low (a gate above its height share) takes the plane's flat shape
    flat = fuse_view(sfm, labels, ndn, None, AutoPriorSettings(ground_guide_height=2.0), intrinsics=K)
    assert flat.report["ground_guide"]["share"] == pytest.approx(1.0)
    assert np.abs(flat.depth[hole] - without.depth[hole]).max() > 0.1


def test_near_ground_that_is_not_a_plane_keeps_the_networks_shape():
    """Inside a crater the nearer labels curve: few lie on any one plane, so the plane would cut
    through the ground and the hole keeps NDN's shape."""
    truth = _ground_depth()
    ground = truth > 0
    columns = np.arange(W, dtype=np.float32)[None, :] * np.ones((H, 1), np.float32)
    curved = np.where(ground, truth * (1 + 0.15 * np.sin(columns / 6.0)), 0.0).astype(np.float32)
    hole = np.zeros((H, W), bool)
    hole[-12:, :] = True
    labels = PriorMaps(depth=np.where(hole, 0.0, curved).astype(np.float32), normal=None, mask=ground & ~hole)
    ndn = PriorMaps(depth=curved, normal=None, mask=ground)
    sfm = np.zeros_like(curved)
    sfm[:-12:4, ::4] = curved[:-12:4, ::4]
    guided = fuse_view(sfm, labels, ndn, ~ground, AutoPriorSettings(), intrinsics=K)
    without = fuse_view(sfm, labels, ndn, ~ground, AutoPriorSettings(ground_guide_angle=0), intrinsics=K)
    assert guided.report["ground_guide"]["inlier_share"] < 0.8
    assert guided.report["ground_guide"]["share"] == 0.0
    np.testing.assert_array_equal(guided.depth, without.depth)
    # told to accept any fit, the plane is used there
    forced = fuse_view(sfm, labels, ndn, ~ground, AutoPriorSettings(ground_guide_inliers=0.0), intrinsics=K)
    assert forced.report["ground_guide"]["share"] > 0.5
