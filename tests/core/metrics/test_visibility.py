"""Which part of a ground-truth mesh the cameras saw (core/metrics/visibility.py), and recall
restricted to it (core/metrics/geometry.py), on scenes whose answer is known by construction."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.metrics import geometry
from esgs.core.metrics.visibility import (CameraView, cameras_from_colmap, depth_map, sample_visibility,
                                          scene_threshold, training_image_names, visible_surface_samples)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] world-to-camera of a camera at ``eye`` looking at ``target`` (x right, y down, z forward)."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = -rotation @ eye
    return matrix


def grid(x0: float, x1: float, y0: float, y1: float, cells: int = 20, z: float = 0.0):
    """A triangulated rectangle at height z: vertices [V, 3], faces [F, 3]."""
    xs, ys = np.linspace(x0, x1, cells + 1), np.linspace(y0, y1, cells + 1)
    xx, yy = np.meshgrid(xs, ys, indexing="ij")
    vertices = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)], axis=1)
    index = np.arange(xx.size).reshape(cells + 1, cells + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    return vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def box(center, size):
    """A closed axis-aligned box: vertices [8, 3], faces [12, 3]."""
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    vertices = np.asarray(center) + corners * np.asarray(size)
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return vertices, faces


def merge(*meshes):
    vertices, faces, offset = [], [], 0
    for v, f in meshes:
        vertices.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(faces)


def camera(world_to_camera, size=(160, 120), focal=120.0) -> CameraView:
    width, height = size
    return CameraView(world_to_camera, focal, focal, width / 2, height / 2, width, height)


def test_samples_behind_a_box_are_hidden_and_those_in_front_are_seen():
    plane = grid(-5, 5, -5, 5)
    vertices, faces = merge(plane, box((0.0, 0.0, 0.5), (1.0, 1.0, 1.0)))
    # low camera on the -x side looking along +x over the box
    view = camera(look_at((-6.0, 0.0, 0.6), (0.0, 0.0, 0.3)))
    samples = np.array([[x, y, 0.0] for x in np.linspace(0.7, 1.5, 5) for y in (-0.2, 0.0, 0.2)]  # in the shadow
                       + [[x, y, 0.0] for x in np.linspace(-3.0, -1.0, 5) for y in (-0.2, 0.0, 0.2)]  # before it
                       + [[-0.5, 0.0, 0.5], [-0.5, 0.2, 0.8]])  # on the box's face towards the camera
    visible = visible_surface_samples(vertices, faces, samples, [view])
    assert not visible[:15].any()
    assert visible[15:].all()
    # without the box, the same ground is seen
    assert visible_surface_samples(*plane, samples[:15], [view]).all()


def test_samples_outside_every_frustum_or_behind_the_camera_are_not_visible():
    vertices, faces = grid(-10, 10, -10, 10)
    # straight down from 2 m with a ~67 degree field of view: sees about |x|, |y| < 1.3
    view = camera(look_at((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)))
    samples = np.array([[0.0, 0.0, 0.0], [0.5, -0.5, 0.0], [5.0, 0.0, 0.0], [-8.0, 8.0, 0.0]])
    np.testing.assert_array_equal(visible_surface_samples(vertices, faces, samples, [view]), [True, True, False, False])
    # a camera under the plane looking down sees nothing of it (all behind it)
    under = camera(look_at((0.0, 0.0, -1.0), (0.0, 0.0, -3.0), up=(0.0, 1.0, 0.0)))
    assert not visible_surface_samples(vertices, faces, samples, [under]).any()
    # two cameras: the union of what each saw
    other = camera(look_at((5.0, 0.0, 2.0), (5.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)))
    visible, distance = sample_visibility(vertices, faces, samples, [view, other])
    np.testing.assert_array_equal(visible, [True, True, True, False])
    np.testing.assert_allclose(distance[:3], [2.0, np.sqrt(2.0**2 + 0.5), 2.0])
    assert np.isinf(distance[3])


def test_depth_map_clips_triangles_that_run_behind_the_camera():
    # a ground plane under a camera 1 m up looking at the horizon: half the plane is behind it
    vertices, faces = grid(-50, 50, -50, 50, cells=2)
    view = camera(look_at((0.0, 0.0, 1.0), (10.0, 0.0, 1.0)))
    depth, scale = depth_map(vertices, faces, view)
    assert scale == 1.0 and depth.shape == (120, 160)
    # below the horizon every pixel shows the ground at depth 1 m / tan(angle below horizon)
    rows = np.arange(60, 120)
    expected = 1.0 / np.tan(np.arctan((rows + 0.5 - 60.0) / 120.0))
    ground = expected < 49.0  # the plane ends 50 m ahead
    np.testing.assert_allclose(depth[rows[ground], 80], expected[ground], rtol=1e-6)
    assert np.isinf(depth[rows[~ground], 80]).all() and ground.sum() > 50
    assert np.isinf(depth[:60]).all()  # sky


def test_recall_counts_only_the_seen_surface():
    # the mesh is twice as large as what the camera sees: the camera sees x < 0 only
    vertices, faces = grid(-2.0, 2.0, -1.0, 1.0, cells=40)
    view = CameraView(look_at((-1.0, 0.0, 1.0), (-1.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)), 100.0, 100.0, 100.0, 100.0,
                      200, 200)  # 90 degree field of view: x in [-2, 0], y in [-1, 1]
    rng = np.random.default_rng(3)
    seen_part = np.column_stack([rng.uniform(-2.0, 0.0, 20000), rng.uniform(-1.0, 1.0, 20000), np.zeros(20000)])
    restricted = geometry.compare_points_to_mesh(seen_part, vertices, faces, threshold_m=0.05,
                                                 n_surface_samples=20000, cameras=[view]).summary
    whole = geometry.compare_points_to_mesh(seen_part, vertices, faces, threshold_m=0.05,
                                            n_surface_samples=20000).summary
    assert restricted["recall"] > 0.98
    assert whole["recall"] == pytest.approx(0.5, abs=0.03)
    assert restricted["precision"] == whole["precision"] == 1.0
    assert restricted["visible_fraction"] == pytest.approx(0.5, abs=0.03)
    assert restricted["n_visible_samples"] == pytest.approx(10000, rel=0.06) and restricted["n_cameras"] == 1
    assert restricted["recall_whole_mesh"] == pytest.approx(whole["recall"], abs=1e-9)
    assert restricted["recall_scope"] == "surface seen by the training cameras"
    assert whole["recall_scope"] == "whole mesh" and "n_visible_samples" not in whole


def test_threshold_scales_with_the_scene():
    # the same scene at two scales: the automatic threshold follows (1 % of the viewing distance)
    vertices, faces = grid(-2.0, 2.0, -2.0, 2.0)
    points = vertices.copy()
    thresholds = []
    for scale in (1.0, 10.0):
        view = camera(look_at((0.0, 0.0, 2.0 * scale), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)))
        summary = geometry.compare_points_to_mesh(points * scale, vertices * scale, faces, threshold_m=None,
                                                  n_surface_samples=2000, cameras=[view]).summary
        thresholds.append(summary["threshold_m"])
        assert "median camera-to-surface distance" in summary["threshold_rule"]
    # the seen ground is 2 to 2.6 m away (straight down to the image corners)
    assert 0.01 * 2.0 < thresholds[0] < 0.01 * 2.4
    assert thresholds[1] == pytest.approx(10 * thresholds[0], rel=1e-6)
    # without cameras: 0.5 % of the bounding-box diagonal; a given threshold is kept
    value, rule = scene_threshold(None, vertices)
    assert value == pytest.approx(0.005 * np.sqrt(32.0)) and "diagonal" in rule
    given = geometry.compare_points_to_mesh(points, vertices, faces, threshold_m=0.2, n_surface_samples=500).summary
    assert given["threshold_m"] == 0.2 and given["threshold_rule"] == "given"


def test_colmap_cameras_and_the_training_split():
    from esgs.core.colmap.model import Camera, ColmapModel, Image

    names = [f"{index:03d}.png" for index in range(10)]
    assert training_image_names(names[::-1], 8) == [name for name in names if name not in ("000.png", "008.png")]
    assert training_image_names(names, 0) == names
    pose = look_at((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    from esgs.core.colmap.geometry import matrix_to_quat_wxyz

    model = ColmapModel(cameras={1: Camera(1, "PINHOLE", 160, 120, np.array([120.0, 120.0, 80.0, 60.0]))},
                        images={i + 1: Image(i + 1, name, 1, matrix_to_quat_wxyz(pose[:3, :3]), pose[:3, 3])
                                for i, name in enumerate(names)}, points={})
    placement = np.eye(4)
    placement[:3, 3] = (0.0, 0.0, 5.0)  # the scene moved up by 5 in the world
    views = cameras_from_colmap(model, ["001.png", "002.png"], world_from_model=placement)
    assert [view.name for view in views] == ["001.png", "002.png"]
    np.testing.assert_allclose(views[0].center, [0.0, 0.0, 7.0], atol=1e-9)
    vertices, faces = grid(-1, 1, -1, 1, z=5.0)
    assert visible_surface_samples(vertices, faces, np.array([[0.0, 0.0, 5.0]]), views)[0]
    # under the plane: hidden by it
    assert not visible_surface_samples(vertices, faces, np.array([[0.0, 0.0, 4.0]]), views)[0]
