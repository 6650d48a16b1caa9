"""The gap z-buffer: labels that look through a removed (gap) triangle of a reconstructed mesh."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.labels.gaps import gap_mesh_path, through_gap, zbuffer_depth
from tests.core.train.scene import look_at

WIDTH, HEIGHT = 64, 48
K = np.array([[50.0, 0, 31.0], [0, 50.0, 24.5], [0, 0, 1]])


def raycast_depth(vertices, triangles, world_to_camera) -> np.ndarray:
    """The reference: trimesh's ray caster, first hit per pixel centre, as camera z."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, triangles, process=False)
    xs, ys = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    rays_camera = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], 1) @ np.linalg.inv(K).T
    camera_to_world = np.linalg.inv(world_to_camera)
    directions = rays_camera @ camera_to_world[:3, :3].T
    origins = np.repeat(camera_to_world[None, :3, 3], len(directions), axis=0)
    locations, ray_index, _ = mesh.ray.intersects_location(origins, directions, multiple_hits=True)
    depth = np.full(xs.size, np.inf)
    z = (locations @ world_to_camera[:3, :3].T + world_to_camera[:3, 3])[:, 2]
    np.minimum.at(depth, ray_index, z)
    return depth.reshape(HEIGHT, WIDTH)


def test_zbuffer_matches_a_ray_caster():
    rng = np.random.default_rng(3)
    centres = rng.uniform([-3, 4, -1], [3, 12, 1], (25, 3))
    vertices = (centres[:, None, :] + rng.normal(0, 1.2, (25, 3, 3))).reshape(-1, 3)
    triangles = np.arange(75).reshape(25, 3)
    world_to_camera = look_at([0.3, -1.0, 0.4], [0.0, 8.0, 0.0])
    ours = zbuffer_depth(vertices, triangles, K, world_to_camera, WIDTH, HEIGHT)
    reference = raycast_depth(vertices, triangles, world_to_camera)
    covered = np.isfinite(reference)
    assert 0.2 < covered.mean() < 0.95
    # pixel centres exactly on an edge may go either way: allow a handful of pixels to differ
    assert (np.isfinite(ours) != covered).sum() <= 0.01 * covered.size
    both = covered & np.isfinite(ours)
    agree = np.isclose(ours[both], reference[both], rtol=1e-6)
    assert agree.mean() > 0.99


def test_zbuffer_clips_triangles_that_reach_behind_the_camera():
    # a ground triangle under and behind the camera: only its front part is seen
    vertices = np.array([[-20.0, -10.0, 0.0], [20.0, -10.0, 0.0], [0.0, 30.0, 0.0]])
    world_to_camera = look_at([0.0, 0.0, 2.0], [0.0, 6.0, 0.0])
    ours = zbuffer_depth(vertices, np.array([[0, 1, 2]]), K, world_to_camera, WIDTH, HEIGHT, near=1e-3)
    reference = raycast_depth(vertices, np.array([[0, 1, 2]]), world_to_camera)
    covered = np.isfinite(reference)
    assert covered[-1].all() and not covered[0].any()  # the ground fills the bottom, not the top
    assert (np.isfinite(ours) != covered).sum() <= 2
    both = covered & np.isfinite(ours)
    np.testing.assert_allclose(ours[both], reference[both], rtol=1e-6)


def test_through_gap_flags_labels_behind_a_gap_only():
    label = np.array([[10.0, 10.0, 0.0, 5.0]])
    gap = np.array([[4.0, np.inf, 3.0, 4.999]])
    flagged = through_gap(label, gap, tolerance=0.01)
    # behind the gap: flagged; no gap on the ray, no label, or the gap at the label itself: kept
    assert flagged.tolist() == [[True, False, False, False]]


def test_gap_mesh_sits_beside_the_mesh(tmp_path):
    assert gap_mesh_path(tmp_path / "mesh" / "reconstructed.ply") == tmp_path / "mesh" / "reconstructed_gaps.ply"


@pytest.mark.parametrize("near", [1e-6, 0.5])
def test_zbuffer_of_nothing_is_infinite(near):
    depth = zbuffer_depth(np.zeros((0, 3)), np.zeros((0, 3), np.int64), K, np.eye(4), WIDTH, HEIGHT, near=near)
    assert depth.shape == (HEIGHT, WIDTH) and np.isinf(depth).all()
