"""Gaussians vs ground-truth mesh in Blender (esgs_addon/compare_mesh.py)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import trimesh  # noqa: E402
from mathutils import Matrix  # noqa: E402

from esgs.core.errors import ConfigError  # noqa: E402
from esgs.core.formats.ply import GaussianPly, write_gaussians_ply  # noqa: E402
from esgs.esgs_addon import compare_mesh, gaussian_nodes, gaussians_import  # noqa: E402
from esgs.esgs_addon.pointcloud import read_point_attribute  # noqa: E402


def mesh_object(name: str, vertices: np.ndarray, faces: np.ndarray, matrix: np.ndarray | None = None):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(vertices.tolist(), [], faces.tolist())
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    if matrix is not None:
        obj.matrix_world = Matrix(matrix.tolist())
    return obj


def gaussians_file(path, means: np.ndarray, opacity_logits: np.ndarray | None = None):
    n = len(means)
    write_gaussians_ply(path, GaussianPly(
        means=means, normals=np.zeros((n, 3)), sh_dc=np.zeros((n, 3)), sh_rest=np.zeros((n, 0, 3)),
        opacity_logit=np.full(n, 4.0) if opacity_logits is None else opacity_logits,
        log_scales=np.full((n, 3), -4.0), quats_wxyz=np.tile([1.0, 0, 0, 0], (n, 1))))
    return path


def rigid(angle: float, translation) -> np.ndarray:
    matrix = np.eye(4)
    c, s = math.cos(angle), math.sin(angle)
    matrix[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    matrix[:3, 3] = translation
    return matrix


def test_plane_distances_and_heat_map(tmp_path):
    # a 4 x 4 m plane at z = 0, placed in the world by a rigid transform; the Gaussians are
    # imported with the same transform, so in the world they sit |z| above or below it
    coords = np.linspace(-2, 2, 5)
    xx, yy = np.meshgrid(coords, coords)
    vertices = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    index = np.arange(25).reshape(5, 5)
    faces = np.concatenate([np.stack([index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel()], 1),
                            np.stack([index[:-1, :-1].ravel(), index[1:, 1:].ravel(), index[1:, :-1].ravel()], 1)])
    placement = rigid(0.7, (3.0, -1.0, 2.0))
    plane = mesh_object("ground truth", vertices, faces, placement)
    rng = np.random.default_rng(0)
    n = 500
    heights = rng.uniform(-0.2, 0.2, n)
    means = np.column_stack([rng.uniform(-1.9, 1.9, (n, 2)), heights])
    logits = np.where(np.abs(heights) > 0.1, -3.0, 3.0)  # the far ones are faint
    obj = gaussians_import.import_gaussians(gaussians_file(tmp_path / "g.ply", means, logits), matrix_world=placement)
    report = tmp_path / "out" / "compare.json"

    summary = compare_mesh.compare_to_mesh(obj, plane, opacity_min=0.5, threshold_m=0.05, out_json=report,
                                           n_surface_samples=5000)
    distances = read_point_attribute(obj, "distance")
    np.testing.assert_allclose(distances, np.abs(heights), atol=1e-5)
    assert summary["frame"] == "world"
    assert summary["gaussians_to_mesh"]["mean"] == pytest.approx(np.abs(heights).mean(), abs=1e-5)
    near = np.abs(heights) <= 0.1
    assert summary["n_gaussians_filtered"] == int(near.sum())
    assert summary["gaussians_to_mesh_filtered"]["mean"] == pytest.approx(np.abs(heights[near]).mean(), abs=1e-5)
    assert summary["precision"] == pytest.approx(np.mean(np.abs(heights[near]) <= 0.05), abs=1e-6)
    assert json.loads(report.read_text()) == summary
    assert compare_mesh.last_comparison(obj) == summary
    # heat map on, red at the 95th percentile of the filtered distances
    assert gaussian_nodes.display_input(obj, "Heat Map")
    assert gaussian_nodes.display_input(obj, "Distance Max") == pytest.approx(
        np.percentile(np.abs(heights[near]), 95), rel=1e-4)


def test_sphere_distances_in_blender_match_analytic(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=3.0)
    mesh = mesh_object("sphere", np.asarray(sphere.vertices), np.asarray(sphere.faces), rigid(0.0, (1.0, 2.0, 3.0)))
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(400, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = rng.uniform(1.0, 5.0, 400)
    # the PLY holds world coordinates here (no placement): centre the points on the sphere's
    means = directions * radii[:, None] + np.array([1.0, 2.0, 3.0])
    obj = gaussians_import.import_gaussians(gaussians_file(tmp_path / "s.ply", means))
    compare_mesh.compare_to_mesh(obj, mesh, n_surface_samples=2000)
    edge = sphere.edges_unique_length.max()
    sagitta = 3.0 - math.sqrt(3.0**2 - (edge / math.sqrt(3)) ** 2)
    np.testing.assert_allclose(read_point_attribute(obj, "distance"), np.abs(radii - 3.0), atol=sagitta + 1e-5)


def test_mesh_file_is_compared_in_the_gaussians_frame(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    mesh_path = tmp_path / "mesh" / "ground_truth.ply"
    mesh_path.parent.mkdir()
    sphere.export(mesh_path)
    means = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 0.0]])
    # placed far away in Blender: a file is in the PLY's frame, so the placement must not count
    obj = gaussians_import.import_gaussians(gaussians_file(tmp_path / "g.ply", means), matrix_world=rigid(1.0, (50, 0, 0)))
    summary = compare_mesh.compare_to_mesh(obj, mesh_path, n_surface_samples=1000, threshold_m=0.1)
    assert summary["frame"] == "gaussians_local"
    distances = read_point_attribute(obj, "distance")
    assert distances[0] == pytest.approx(1.0, abs=0.02)
    assert distances[1] == pytest.approx(1.0, abs=0.05)


def test_bad_inputs(tmp_path):
    plane = mesh_object("plane", np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))
    with pytest.raises(ConfigError, match="not an imported Gaussian"):
        compare_mesh.compare_to_mesh(plane, plane)
    obj = gaussians_import.import_gaussians(gaussians_file(tmp_path / "g.ply", np.zeros((3, 3))))
    with pytest.raises(ConfigError, match="not a mesh"):
        compare_mesh.compare_to_mesh(obj, obj)
    assert "distance" not in obj.data.attributes


def test_operator(tmp_path):
    plane = mesh_object("plane", np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float),
                        np.array([[0, 1, 2], [0, 2, 3]]))
    means = np.array([[0.0, 0.0, 0.01], [0.5, 0.5, -0.02], [0.2, -0.3, 0.5]])
    obj = gaussians_import.import_gaussians(gaussians_file(tmp_path / "g.ply", means))
    bpy.context.view_layer.objects.active = plane
    with pytest.raises(RuntimeError, match="Gaussian point cloud"):
        bpy.ops.esgs.compare_to_mesh(mesh="plane")
    bpy.context.view_layer.objects.active = obj
    with pytest.raises(RuntimeError, match="ground-truth mesh"):
        bpy.ops.esgs.compare_to_mesh()
    settings = bpy.context.scene.esgs.gaussians
    settings.mesh = plane
    settings.threshold = 0.05
    settings.surface_samples = 1000
    settings.report_path = str(tmp_path / "report.json")
    assert bpy.ops.esgs.compare_to_mesh() == {"FINISHED"}
    np.testing.assert_allclose(read_point_attribute(obj, "distance"), [0.01, 0.02, 0.5], atol=1e-6)
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["precision"] == pytest.approx(2 / 3)
    assert report["mesh"] == "plane"


def test_operator_reports_a_missing_dependency(tmp_path, monkeypatch):
    from esgs.operators import compare_to_mesh as operator_module

    def without_scipy(*args, **kwargs):
        raise ModuleNotFoundError("No module named 'scipy'", name="scipy")

    monkeypatch.setattr(operator_module, "compare_to_mesh", without_scipy)
    plane = mesh_object("plane", np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))
    obj = gaussians_import.import_gaussians(gaussians_file(tmp_path / "g.ply", np.zeros((2, 3))))
    bpy.context.view_layer.objects.active = obj
    with pytest.raises(RuntimeError, match="needs scipy"):
        bpy.ops.esgs.compare_to_mesh(mesh=plane.name)


def seen_half_scene(tmp_path):
    """A 20 x 10 m ground plane whose training cameras (straight down from 5 m, 90 degree
    field of view) see only the half x < 0; a run folder naming the scene; Gaussians that
    cover exactly that half."""
    from esgs.core.colmap.geometry import matrix_to_quat_wxyz
    from esgs.core.colmap.io import write_model
    from esgs.core.colmap.model import Camera, ColmapModel, Image
    from tests.blender.colmap_helpers import look_at

    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    pose = look_at(np.array([-5.0, 0.0, 5.0]), np.array([-5.0, 0.0, 0.0]), down_hint=np.array([0.0, -1.0, 0.0]))
    images = {index: Image(index, name, 1, matrix_to_quat_wxyz(pose[:3, :3]), pose[:3, 3])
              for index, name in enumerate(("a.png", "b.png", "c.png"), start=1)}
    write_model(ColmapModel(cameras={1: Camera(1, "PINHOLE", 200, 200, np.array([100.0, 100.0, 100.0, 100.0]))},
                            images=images, points={}), scene / "sparse" / "0")
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"scene": str(scene), "test_every": 0}))
    plane = mesh_object("ground truth", np.array([[-10, -5, 0], [10, -5, 0], [10, 5, 0], [-10, 5, 0]], float),
                        np.array([[0, 1, 2], [0, 2, 3]]))
    xx, yy = np.meshgrid(np.arange(-10.0, 0.0, 0.04) + 0.02, np.arange(-5.0, 5.0, 0.04) + 0.02)
    means = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    obj = gaussians_import.import_gaussians(gaussians_file(tmp_path / "g.ply", means))
    obj["esgs_run_dir"] = str(run)
    return plane, obj


def test_compare_counts_recall_over_the_seen_surface_and_shows_a_legend(tmp_path, capfd):
    plane, obj = seen_half_scene(tmp_path)
    settings = bpy.context.scene.esgs.gaussians
    assert settings.threshold == 0.0 and settings.seen_surface_only  # the defaults: scaled, seen surface
    settings.mesh = plane
    settings.surface_samples = 4000
    bpy.context.view_layer.objects.active = obj
    capfd.readouterr()
    assert bpy.ops.esgs.compare_to_mesh() == {"FINISHED"}
    printed = capfd.readouterr()
    report = printed.out + printed.err
    summary = compare_mesh.last_comparison(obj)
    assert summary["recall"] > 0.97 and summary["recall_whole_mesh"] == pytest.approx(0.5, abs=0.05)
    assert summary["visible_fraction"] == pytest.approx(0.5, abs=0.05) and summary["n_cameras"] == 3
    assert "3 training views of scene" in summary["cameras"]
    # 1 % of the median distance from (-5, 0, 5) to the half it sees: between 5 and 8.7 m
    assert 0.05 < summary["threshold_m"] < 0.087
    assert f"at {summary['threshold_m']:.4g} m (1% of the median camera-to-surface distance" in report
    assert f"recall over the {summary['visible_fraction']:.0%} of the mesh the training cameras saw" in report

    # the heat map's legend: colour bar and labels in metres, beside the cloud, in its collection
    distance_max = gaussian_nodes.display_input(obj, "Distance Max")
    bar, *labels = compare_mesh.legend_objects(obj)
    assert bar.type == "MESH" and bar.name == summary["legend"]
    assert bar[compare_mesh.PROP_LEGEND_MIN] == 0.0
    assert bar[compare_mesh.PROP_LEGEND_MAX] == pytest.approx(distance_max)
    assert compare_mesh.LEGEND_COLOUR_ATTRIBUTE in bar.data.color_attributes
    assert {label.data.body for label in labels} == {"0 m", f"{distance_max:.3g} m", "distance to mesh"}
    for legend_object in [bar] + labels:
        assert legend_object.parent == obj
        assert set(legend_object.users_collection) == set(obj.users_collection)
    # a second comparison replaces the legend rather than adding one
    compare_mesh.compare_to_mesh(obj, plane, n_surface_samples=1000, threshold_m=0.1)
    assert len(compare_mesh.legend_objects(obj)) == 4  # the bar and its three labels


def test_compare_without_training_cameras_says_so(tmp_path):
    plane, obj = seen_half_scene(tmp_path)
    del obj["esgs_run_dir"]
    summary = compare_mesh.compare_to_mesh(obj, plane, n_surface_samples=2000)
    assert summary["recall_scope"] == "whole mesh" and summary["recall"] == pytest.approx(0.5, abs=0.05)
    assert "no training cameras known" in summary["cameras"]
    assert "diagonal" in summary["threshold_rule"]
    assert "recall over the whole mesh" in compare_mesh.describe(summary)
