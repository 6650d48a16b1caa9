"""Label rendering in Blender: exact-mesh labels reproduce the ground truth, holes are
filled and flagged, the reconstruction beats a trivial baseline, failures leave nothing."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
trimesh = pytest.importorskip("trimesh")

from esgs.core.errors import DatasetError  # noqa: E402
from esgs.core.formats.imageio import read_depth_exr, read_image, read_normal_exr  # noqa: E402
from esgs.core.labels.fill import FILLED, RENDERED  # noqa: E402
from esgs.core.terrain import RenderConfig, RigConfig, SceneConfig, TerrainConfig  # noqa: E402

from .test_render_dataset import build_and_render  # noqa: E402


def arc_config() -> SceneConfig:
    """A 40 m cratered, rocky terrain; 6 views on a 60-degree orbit arc at 128x72 (stereo-friendly)."""
    config = SceneConfig(
        name="tiny_arc", seed=11, sky=True,
        terrain=TerrainConfig(resolution=129, extent_m=40.0, relief_amplitude_m=1.0, relief_wavelength_m=20.0,
                              crater_count=6, crater_max_diameter_m=8.0, rock_abundance=0.08,
                              rock_min_diameter_m=0.4, rock_max_diameter_m=1.5),
        rig=RigConfig(kind="orbit", views=6, radius_m=10.0, height_m=4.0, sweep_deg=60.0),
        render=RenderConfig(width=128, height=72, samples=4, camera="custom"),
    )
    config.validate()
    return config


@pytest.fixture(scope="module")
def scene_template(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("labels") / "scene"
    build_and_render(out, arc_config())
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return out


@pytest.fixture
def scene(scene_template, tmp_path) -> Path:
    copy = tmp_path / "scene"
    shutil.copytree(scene_template, copy)
    return copy


def _maps(scene: Path, source: str, stem: str):
    depth, depth_header = read_depth_exr(scene / "priors" / source / "depth" / f"{stem}.exr")
    normal, _ = read_normal_exr(scene / "priors" / source / "normal" / f"{stem}.exr")
    mask = read_image(scene / "priors" / source / "mask" / f"{stem}.png")
    return depth, normal, mask, depth_header


def _stems(scene: Path) -> list[str]:
    return sorted(p.stem for p in (scene / "priors" / "gt" / "depth").glob("*.exr"))


def _blender_blocks() -> dict[str, int]:
    return {name: len(getattr(bpy.data, name)) for name in ("scenes", "objects", "meshes", "cameras", "node_groups")}


def test_exact_mesh_labels_reproduce_the_ground_truth(scene):
    from esgs.esgs_addon.render_labels import render_labels

    before = _blender_blocks()
    report = render_labels(scene, scene / "mesh" / "ground_truth.ply")
    assert _blender_blocks() == before  # the temporary scene and everything in it are gone
    assert len(report["views"]) == 6 and report["method"] == "mesh"
    for stem in _stems(scene):
        truth, truth_normal, truth_mask, _ = _maps(scene, "gt", stem)
        depth, normal, mask, header = _maps(scene, "labels", stem)
        surface = truth > 0
        assert 0.2 < surface.mean() < 1.0  # the views see both ground and sky
        rendered = mask == RENDERED
        assert np.mean(rendered == surface) > 0.999  # same surface pixels; sky stays empty
        both = rendered & surface
        relative = np.abs(depth[both] - truth[both]) / truth[both]
        assert np.median(relative) <= 1e-3
        cosine = np.clip(np.sum(normal[both] * truth_normal[both], axis=-1), -1, 1)
        assert np.degrees(np.median(np.arccos(cosine))) < 1.0
        assert header["source"] == "labels" and header["mesh"].endswith("ground_truth.ply")


def test_a_hole_in_the_mesh_is_filled_and_flagged(scene):
    from esgs.esgs_addon.render_labels import render_labels

    mesh = trimesh.load(scene / "mesh" / "ground_truth.ply", process=False)
    # cut a hole where the first view sees smooth ground (no depth edge near it)
    truth, _, _, _ = _maps(scene, "gt", _stems(scene)[0])
    from scipy.ndimage import generic_filter

    from esgs.core.colmap import read_model

    model = read_model(scene)
    image = next(i for i in model.sorted_images() if Path(i.name).stem == _stems(scene)[0])
    camera = model.cameras[image.camera_id]
    roughness = generic_filter(np.where(truth > 0, truth, 1e3), np.ptp, size=15) / np.maximum(truth, 1e-3)
    roughness[: truth.shape[0] // 2] = np.inf  # the lower half: near ground, seen from above
    roughness[-16:], roughness[:, :16], roughness[:, -16:] = np.inf, np.inf, np.inf  # a hole inside the image
    row, col = np.unravel_index(np.argmin(roughness), truth.shape)
    z = truth[row, col]
    point_camera = np.linalg.inv(camera.K()) @ np.array([col + 0.5, row + 0.5, 1.0]) * z
    world_to_camera = image.world_to_camera()
    point = world_to_camera[:3, :3].T @ (point_camera - world_to_camera[:3, 3])
    centroids = mesh.vertices[mesh.faces].mean(axis=1)
    keep = np.linalg.norm(centroids[:, :2] - point[:2], axis=1) > 0.6
    holed = scene / "holed.ply"
    trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False).export(holed)
    render_labels(scene, holed)
    depth, normal, mask, header = _maps(scene, "labels", _stems(scene)[0])
    filled = mask == FILLED
    assert filled.sum() > 20 and int(header["filled_pixels"]) == filled.sum()
    relative = np.abs(depth[filled] - truth[filled]) / truth[filled]
    assert np.median(relative) < 0.02  # terrain under a 1.2 m hole is close to its surroundings
    np.testing.assert_allclose(np.linalg.norm(normal[filled], axis=-1), 1.0, atol=1e-4)


def test_reconstructed_mesh_labels_beat_a_trivial_baseline(scene):
    from esgs.core.labels.accuracy import label_accuracy
    from esgs.core.labels.reconstruct import reconstruct_mesh
    from esgs.core.labels.stereo import StereoOptions
    from esgs.core.labels.reconstruct import ReconstructOptions
    from esgs.esgs_addon.render_labels import render_labels

    result = reconstruct_mesh(scene, ReconstructOptions(stereo=StereoOptions(planes=64, neighbours=3)))
    render_labels(scene, result["mesh"], method="reconstruct")
    accuracy = label_accuracy(scene)
    baseline = accuracy["baseline_median_depth"]
    assert accuracy["coverage"] > 0.5
    assert accuracy["overall"]["abs_rel"] < 0.25 * baseline["abs_rel"]
    assert accuracy["overall"]["delta1"] > baseline["delta1"] and accuracy["overall"]["delta1"] > 0.95


def test_missing_mesh_and_scene_without_cameras_write_nothing(scene, tmp_path):
    from esgs.core.colmap import ColmapModel, write_model
    from esgs.esgs_addon.render_labels import render_labels

    before = _blender_blocks()
    with pytest.raises(DatasetError, match="mesh file not found"):
        render_labels(scene, scene / "missing.ply")
    assert not (scene / "priors" / "labels").exists() and not list(scene.glob(".labels*"))
    mesh = trimesh.load(scene / "mesh" / "ground_truth.ply", process=False)
    elsewhere = scene / "elsewhere.ply"
    trimesh.Trimesh(mesh.vertices + np.array([0.0, 0.0, 500.0]), mesh.faces, process=False).export(elsewhere)
    with pytest.raises(DatasetError, match="no camera sees the mesh"):
        render_labels(scene, elsewhere)  # e.g. a mesh in another frame or unit
    assert not (scene / "priors" / "labels").exists() and not list(scene.glob(".labels*"))
    empty = tmp_path / "empty"
    model = ColmapModel({}, {}, {})
    write_model(model, empty / "sparse" / "0")
    with pytest.raises(DatasetError, match="no registered images|no images"):
        render_labels(empty, scene / "mesh" / "ground_truth.ply")
    assert _blender_blocks() == before


def test_a_failure_mid_run_keeps_the_previous_labels(scene, monkeypatch):
    from esgs.core.labels import writer as writer_module
    from esgs.esgs_addon.render_labels import render_labels

    render_labels(scene, scene / "mesh" / "ground_truth.ply")
    labels = scene / "priors" / "labels"
    before = {p: p.read_bytes() for p in labels.rglob("*") if p.is_file()}
    original = writer_module.LabelWriter.add
    calls = []

    def failing_add(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise DatasetError("simulated failure on the third view")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(writer_module.LabelWriter, "add", failing_add)
    blocks = _blender_blocks()
    with pytest.raises(DatasetError, match="simulated"):
        render_labels(scene, scene / "mesh" / "ground_truth.ply", smooth=False)
    assert {p: p.read_bytes() for p in labels.rglob("*") if p.is_file()} == before
    assert not list(scene.glob(".labels*")) and _blender_blocks() == blocks


def test_operator_renders_labels_headless(scene):
    settings = bpy.context.scene.esgs.labels
    settings.scene_dir = str(scene)
    settings.mesh_path = str(scene / "mesh" / "ground_truth.ply")
    assert bpy.ops.esgs.render_labels() == {"FINISHED"}
    assert len(list((scene / "priors" / "labels" / "depth").glob("*.exr"))) == 6
    info = json.loads((scene / "priors" / "labels" / "labels.json").read_text())
    assert info["method"] == "mesh" and "gap_mesh" not in info
    with pytest.raises(RuntimeError, match="mesh file not found"):
        bpy.ops.esgs.render_labels(scene_dir=str(scene), mesh_path=str(scene / "nothing.ply"))
    # rebuilt from the images: the gap mesh written beside the mesh is used too
    assert bpy.ops.esgs.render_labels(scene_dir=str(scene), reconstruct=True) == {"FINISHED"}
    info = json.loads((scene / "priors" / "labels" / "labels.json").read_text())
    gaps = scene / "mesh" / "reconstructed_gaps.ply"
    assert info["method"] == "reconstruct" and gaps.is_file() and info["gap_mesh"] == str(gaps.resolve())


def test_labels_command_runs_blender_in_a_child_and_reports(scene, capsys):
    from esgs.core.cli import main

    assert main(["labels", str(scene), "--mesh", str(scene / "mesh" / "ground_truth.ply"), "--report"]) == 0
    table = capsys.readouterr().out
    assert "AbsRel" in table
    accuracy = json.loads((scene / "priors" / "labels" / "accuracy.json").read_text())
    assert accuracy["overall"]["abs_rel"] < 1e-3 and accuracy["overall"]["delta1"] == 1.0


def test_labels_seen_through_a_gap_are_dropped(scene, tmp_path):
    """A hole cut in the true terrain, a floor 6 m below it: without the gap mesh the hole's
    pixels are labelled with the floor (far too deep); with it they are dropped and every
    label left matches the truth."""
    from esgs.core.labels.fill import FillOptions
    from esgs.core.labels.gaps import zbuffer_depth
    from esgs.core.labels.mesh_io import load_mesh, write_mesh
    from esgs.core.colmap.io import read_model
    from esgs.esgs_addon.render_labels import render_labels

    vertices, triangles = load_mesh(scene / "mesh" / "ground_truth.ply")
    centroids = vertices[triangles].mean(axis=1)
    hole = np.hypot(centroids[:, 0], centroids[:, 1]) < 4.0  # the orbit's centre: seen by every view
    low = vertices[:, 2].min() - 6.0
    floor = np.array([[-60, -60, low], [60, -60, low], [60, 60, low], [-60, 60, low]], np.float64)
    holed_vertices = np.concatenate([vertices, floor])
    holed_triangles = np.concatenate([triangles[~hole], len(vertices) + np.array([[0, 1, 2], [0, 2, 3]])])
    write_mesh(tmp_path / "holed.ply", holed_vertices, holed_triangles)
    write_mesh(tmp_path / "gaps.ply", vertices, triangles[hole])
    no_fill = FillOptions(max_hole_fraction=0.0)
    model = read_model(scene)
    errors = {}
    for name, gaps in (("without", None), ("with", tmp_path / "gaps.ply")):
        report = render_labels(scene, tmp_path / "holed.ply", fill=no_fill, gaps_path=gaps)
        worst, flagged = [], 0.0
        for image, view in zip(model.sorted_images(), report["views"]):
            stem = Path(image.name).stem
            label, _, mask, _ = _maps(scene, "labels", stem)
            truth, _, truth_mask, _ = _maps(scene, "gt", stem)
            both = (mask == RENDERED) & (truth > 0)
            worst.append(np.max(np.abs(label[both] - truth[both]) / truth[both]))
            flagged += view["through_gap_fraction"]
            if gaps is not None:  # nothing rendered is left behind a gap triangle
                gap_depth = zbuffer_depth(*load_mesh(gaps), model.cameras[image.camera_id].K(), image.world_to_camera(),
                                          label.shape[1], label.shape[0])
                assert not np.any((mask == RENDERED) & (gap_depth < label * 0.99))
        errors[name] = (max(worst), flagged)
        assert ("gap_mesh" in report) == (gaps is not None)
    assert errors["without"][0] > 0.5 and errors["without"][1] == 0.0  # the floor seen through the hole
    assert errors["with"][0] < 0.02 and errors["with"][1] > 0.0


def test_the_label_job_drops_labels_seen_through_gaps_of_its_reconstruction(scene):
    from esgs.core.labels.pipeline import LabelJob, run_label_job
    from esgs.core.labels.reconstruct import ReconstructOptions
    from esgs.core.labels.stereo import StereoOptions

    job = LabelJob(scene=scene, reconstruct=True, report=True,
                   reconstruct_options=ReconstructOptions(stereo=StereoOptions(planes=64, neighbours=3)))
    result = run_label_job(job)
    gaps = result["reconstruction"]["gaps"]
    assert gaps is not None and Path(gaps).is_file()
    assert result["labels"]["gap_mesh"] == str(Path(gaps).resolve())
    assert all("through_gap_fraction" in view for view in result["labels"]["views"])
    assert result["accuracy"]["overall"]["delta1"] > 0.95
