"""Gaussian centres <-> mesh distances and scores (core/metrics/geometry.py) against analytic values."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from esgs.core.metrics import geometry as compare
from esgs.core.errors import ConfigError, DatasetError


def grid_plane(half_size: float = 1.0, cells: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """The square [-h, h]^2 at z = 0 as a triangulated grid."""
    coords = np.linspace(-half_size, half_size, cells + 1)
    xx, yy = np.meshgrid(coords, coords, indexing="ij")
    vertices = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], axis=1)
    index = np.arange(xx.size).reshape(cells + 1, cells + 1)
    a, b = index[:-1, :-1].ravel(), index[1:, :-1].ravel()
    c, d = index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return vertices, faces


def test_plane_distances_are_analytic():
    vertices, faces = grid_plane()
    rng = np.random.default_rng(1)
    inside = np.column_stack([rng.uniform(-0.99, 0.99, (500, 2)), rng.uniform(-0.5, 0.5, 500)])
    # beyond the edge x = 1 the closest point is on the border: distance sqrt(dx^2 + z^2)
    beyond = np.column_stack([rng.uniform(1.05, 2.0, 200), rng.uniform(-0.9, 0.9, 200), rng.uniform(-0.5, 0.5, 200)])
    distances = compare.point_to_mesh_distances(np.concatenate([inside, beyond]), vertices, faces)
    expected = np.concatenate([np.abs(inside[:, 2]), np.hypot(beyond[:, 0] - 1.0, beyond[:, 2])])
    np.testing.assert_allclose(distances, expected, atol=1e-12)


def test_sphere_distances_match_the_polyhedron_and_the_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=2.0)
    rng = np.random.default_rng(2)
    directions = rng.normal(size=(2000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = rng.uniform(0.5, 4.0, size=2000)
    points = directions * radii[:, None]
    distances = compare.point_to_mesh_distances(points, sphere.vertices, sphere.faces)
    # the polyhedron lies within its sagitta of the true sphere
    edge = sphere.edges_unique_length.max()
    sagitta = 2.0 - np.sqrt(2.0**2 - (edge / np.sqrt(3)) ** 2)
    np.testing.assert_allclose(distances, np.abs(radii - 2.0), atol=sagitta + 1e-9)
    # and exactly what trimesh's independent closest-point search finds on the polyhedron
    _, reference, _ = trimesh.proximity.closest_point(sphere, points)
    np.testing.assert_allclose(distances, reference, atol=1e-9)


@pytest.mark.parametrize("use_numba", [True, False], ids=["numba", "numpy"])
def test_irregular_mesh_with_huge_and_tiny_triangles_matches_trimesh(use_numba, monkeypatch):
    monkeypatch.setattr(compare, "USE_NUMBA", use_numba)
    rng = np.random.default_rng(3)
    sphere = trimesh.creation.icosphere(subdivisions=3)
    sphere.vertices += rng.normal(scale=0.05, size=sphere.vertices.shape)
    big = trimesh.Trimesh([[-50, -50, -3], [50, -50, -3], [0, 60, -3]], [[0, 1, 2]])
    degenerate = trimesh.Trimesh([[5, 5, 5], [5, 5, 5], [6, 5, 5]], [[0, 1, 2]], process=False)
    mesh = trimesh.util.concatenate([sphere, big, degenerate])
    points = rng.uniform(-8, 8, size=(3000, 3))
    distances = compare.point_to_mesh_distances(points, mesh.vertices, mesh.faces)
    _, reference, _ = trimesh.proximity.closest_point(mesh, points)
    np.testing.assert_allclose(distances, reference, atol=1e-9)


def test_closest_points_cover_every_region():
    a, b, c = np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0])
    queries = np.array([[-1, -1, 1], [2, -1, 0], [-1, 2, 0], [0.5, -1, 0], [-1, 0.5, 0], [1, 1, 0], [0.2, 0.2, 3]], float)
    expected = np.array([a, b, c, [0.5, 0, 0], [0, 0.5, 0], [0.5, 0.5, 0], [0.2, 0.2, 0]])
    n = len(queries)
    got = compare.closest_points_on_triangles(queries, np.tile(a, (n, 1)), np.tile(b, (n, 1)), np.tile(c, (n, 1)))
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_statistics_scores_and_opacity_filter():
    vertices, faces = grid_plane(half_size=1.0, cells=4)
    rng = np.random.default_rng(4)
    n = 4000
    points = np.column_stack([rng.uniform(-1, 1, (n, 2)), np.zeros(n)])
    offsets = np.where(np.arange(n) < n // 2, 0.01, 0.3)  # half close, half far
    points[:, 2] = offsets
    opacities = np.where(offsets < 0.1, 0.9, 0.05)  # the far half is nearly transparent
    result = compare.compare_points_to_mesh(points, vertices, faces, opacities=opacities, opacity_min=0.5,
                                            threshold_m=0.05, n_surface_samples=20000, seed=7)
    summary = result.summary
    np.testing.assert_allclose(result.distances, offsets, atol=1e-12)
    everything = summary["gaussians_to_mesh"]
    assert everything["count"] == n
    assert everything["mean"] == pytest.approx(0.155)
    assert everything["std"] == pytest.approx(0.145)
    assert everything["median"] == pytest.approx(0.155)
    assert everything["p95"] == pytest.approx(0.3)
    assert everything["rms"] == pytest.approx(np.sqrt((0.01**2 + 0.3**2) / 2))
    filtered = summary["gaussians_to_mesh_filtered"]
    assert filtered["count"] == n // 2 and filtered["mean"] == pytest.approx(0.01) and filtered["std"] == pytest.approx(0)
    assert summary["opacity_min"] == 0.5 and summary["threshold_m"] == 0.05
    assert summary["precision"] == 1.0
    # 2000 near centres over 4 m^2 leave gaps: recall is high but below 1, and F follows
    assert 0.8 < summary["recall"] <= 1.0
    assert summary["fscore"] == pytest.approx(2 * summary["recall"] / (1 + summary["recall"]))
    json.dumps(summary)  # plain JSON types only


def test_scores_are_undefined_when_no_centre_passes_the_opacity_filter():
    vertices, faces = grid_plane(half_size=1.0, cells=4)
    points = np.array([[0.0, 0.0, 0.01], [0.5, 0.5, 0.02]])
    result = compare.compare_points_to_mesh(points, vertices, faces, opacities=np.array([0.1, 0.2]), opacity_min=0.5,
                                            threshold_m=0.05, n_surface_samples=500)
    summary = result.summary
    assert summary["n_gaussians_filtered"] == 0
    assert summary["precision"] is None and summary["recall"] is None and summary["fscore"] is None
    np.testing.assert_allclose(result.distances, [0.01, 0.02], atol=1e-12)  # the unfiltered figures stay
    json.dumps(summary)


def test_recall_drops_when_part_of_the_surface_is_missing():
    vertices, faces = grid_plane(half_size=1.0, cells=4)
    coords = np.linspace(-1, 1, 81)
    xx, yy = np.meshgrid(coords, coords)
    points = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    half = points[points[:, 0] < 0]  # only the x < 0 half reconstructed
    result = compare.compare_points_to_mesh(half, vertices, faces, threshold_m=0.03, n_surface_samples=40000)
    assert result.summary["precision"] == 1.0
    assert result.summary["recall"] == pytest.approx(0.5 + 0.03 / 2, abs=0.02)
    assert result.summary["opacity_min"] is None


def test_surface_samples_are_uniform_by_area():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [13, 0, 0], [10, 3, 0]], float)
    faces = np.array([[0, 1, 2], [3, 4, 5]])  # areas 0.5 and 4.5
    samples = compare.sample_mesh_surface(vertices, faces, 20000, seed=0)
    on_big = np.mean(samples[:, 0] >= 10)
    assert on_big == pytest.approx(0.9, abs=0.01)
    small = samples[samples[:, 0] < 10]
    assert np.all(small[:, 0] + small[:, 1] <= 1 + 1e-12) and np.all(small >= -1e-12)


def test_bad_inputs_are_clear_errors(tmp_path):
    vertices, faces = grid_plane()
    with pytest.raises(DatasetError, match="no triangles"):
        compare.point_to_mesh_distances(np.zeros((1, 3)), vertices, np.zeros((0, 3), int))
    with pytest.raises(DatasetError, match="do not exist"):
        compare.point_to_mesh_distances(np.zeros((1, 3)), vertices, faces + 1000)
    with pytest.raises(ConfigError, match="threshold"):
        compare.compare_points_to_mesh(np.zeros((1, 3)), vertices, faces, threshold_m=0)
    with pytest.raises(ConfigError, match="opacities"):
        compare.compare_points_to_mesh(np.zeros((2, 3)), vertices, faces, opacities=np.ones(3))
    with pytest.raises(DatasetError, match="not found"):
        compare.load_mesh(tmp_path / "missing.ply")
    points_only = tmp_path / "points.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(points_only)
    with pytest.raises(DatasetError, match="no triangles"):
        compare.load_mesh(points_only)


def test_load_mesh_reads_back_a_written_mesh(tmp_path):
    vertices, faces = grid_plane(cells=3)
    path = tmp_path / "plane.ply"
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    loaded_vertices, loaded_faces = compare.load_mesh(path)
    np.testing.assert_allclose(loaded_vertices, vertices, atol=1e-6)
    np.testing.assert_array_equal(loaded_faces, faces)


def test_cli_reports_and_writes_json(tmp_path, capsys):
    from esgs.core.cli import main
    from esgs.core.formats.ply import GaussianPly, write_gaussians_ply

    vertices, faces = grid_plane(cells=2)
    mesh_path = tmp_path / "gt.ply"
    trimesh.Trimesh(vertices, faces, process=False).export(mesh_path)
    n = 50
    rng = np.random.default_rng(5)
    means = np.column_stack([rng.uniform(-0.9, 0.9, (n, 2)), np.full(n, 0.02)])
    logits = np.where(np.arange(n) < 10, -5.0, 5.0)  # 10 nearly transparent Gaussians
    write_gaussians_ply(tmp_path / "g.ply", GaussianPly(
        means=means, normals=np.zeros((n, 3)), sh_dc=np.zeros((n, 3)), sh_rest=np.zeros((n, 0, 3)),
        opacity_logit=logits, log_scales=np.zeros((n, 3)), quats_wxyz=np.tile([1.0, 0, 0, 0], (n, 1))))
    out = tmp_path / "report" / "compare.json"
    code = main(["compare", str(tmp_path / "g.ply"), str(mesh_path), "--threshold", "0.03", "--samples", "1000",
                 "--out", str(out)])
    assert code == 0
    report = json.loads(out.read_text())
    assert report["gaussians_to_mesh"]["mean"] == pytest.approx(0.02, abs=1e-6)
    assert report["n_gaussians_filtered"] == 40 and report["precision"] == 1.0
    assert json.loads(capsys.readouterr().out) == report
    assert main(["compare", str(mesh_path), str(mesh_path)]) == 1  # a mesh is not a Gaussian PLY


def test_cli_restricts_recall_to_what_the_training_cameras_saw(tmp_path, capsys):
    from esgs.core.cli import main
    from esgs.core.colmap.geometry import matrix_to_quat_wxyz
    from esgs.core.colmap.io import write_model
    from esgs.core.colmap.model import Camera, ColmapModel, Image
    from esgs.core.formats.ply import GaussianPly, write_gaussians_ply

    # a 4 x 2 m plane; two training cameras look straight down at its x < 0 half
    vertices, faces = grid_plane(cells=8)
    vertices = vertices * np.array([2.0, 1.0, 1.0])
    mesh_path = tmp_path / "gt.ply"
    trimesh.Trimesh(vertices, faces, process=False).export(mesh_path)
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking down -z, image y along world -y
    images = {}
    for index, x in enumerate((-1.0, -1.0, -1.0)):  # image 0 is held out, 1 and 2 train
        centre = np.array([x, 0.0, 1.0])
        images[index + 1] = Image(index + 1, f"{index:03d}.png", 1, matrix_to_quat_wxyz(pose[:3, :3]),
                                  -pose[:3, :3] @ centre)
    model = ColmapModel(cameras={1: Camera(1, "PINHOLE", 200, 200, np.array([100.0, 100.0, 100.0, 100.0]))},
                        images=images, points={})
    write_model(model, tmp_path / "scene" / "sparse" / "0")
    n = 4000
    rng = np.random.default_rng(2)
    means = np.column_stack([rng.uniform(-2.0, 0.0, n), rng.uniform(-1.0, 1.0, n), np.zeros(n)])
    write_gaussians_ply(tmp_path / "g.ply", GaussianPly(
        means=means, normals=np.zeros((n, 3)), sh_dc=np.zeros((n, 3)), sh_rest=np.zeros((n, 0, 3)),
        opacity_logit=np.full(n, 5.0), log_scales=np.zeros((n, 3)), quats_wxyz=np.tile([1.0, 0, 0, 0], (n, 1))))
    assert main(["compare", str(tmp_path / "g.ply"), str(mesh_path), "--samples", "4000"]) == 0
    whole = json.loads(capsys.readouterr().out)
    assert main(["compare", str(tmp_path / "g.ply"), str(mesh_path), "--samples", "4000", "--threshold", "0.05",
                 "--scene", str(tmp_path / "scene")]) == 0
    seen = json.loads(capsys.readouterr().out)
    assert whole["recall"] == pytest.approx(0.5, abs=0.05) and whole["threshold_m"] == 0.05
    assert seen["recall"] > 0.95 and seen["n_cameras"] == 2 and seen["scene"] == str(tmp_path / "scene")
    # without --threshold the match distance follows the scene: 1 % of the ~1 m viewing distance
    assert main(["compare", str(tmp_path / "g.ply"), str(mesh_path), "--samples", "4000",
                 "--scene", str(tmp_path / "scene")]) == 0
    scaled = json.loads(capsys.readouterr().out)
    assert 0.009 < scaled["threshold_m"] < 0.015 and "camera-to-surface" in scaled["threshold_rule"]
