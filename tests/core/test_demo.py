"""The main job: which ESGS losses each prior source drives, the priors stage with the shipped
NDN weights, the report's geometry section for dense relative priors, and (slow) the whole
chain at toy size."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from esgs.core.apps import demo, report
from esgs.core.config import config_from_dict, config_to_dict
from esgs.core.apps.demo import DemoConfig, esgs_settings
from esgs.core.errors import ConfigError
from esgs.core.methods import AUTO_DEPTH_WEIGHT, AUTO_PRIOR_POINTS, ESGSConfig, full_esgs
from esgs.core.priors import PriorMaps, load_prior_maps, write_prior_maps
from tests.core.train.scene import make_scene


# --- settings ----------------------------------------------------------------------------
def _switches(settings: dict) -> dict:
    return {name: settings[name] for name in ("priors", "depth", "normal", "consistency", "gpdfn")}


def test_the_demo_trains_full_esgs_on_auto_priors_by_default():
    assert DemoConfig().priors == "auto" and DemoConfig().sparse_points == "triangulated"
    settings = esgs_settings(DemoConfig().priors)
    # the full method exactly as full_esgs defines it, weights included (auto: depth weight 3)
    assert config_from_dict(ESGSConfig, settings) == full_esgs("auto") == full_esgs()
    assert settings["depth_weight"] == AUTO_DEPTH_WEIGHT and settings == esgs_settings()
    # Gaussians seeded from the auto prior's depth; sources it was not measured with seed none
    assert settings["prior_points"] == AUTO_PRIOR_POINTS > 0 and full_esgs("gt").prior_points == 0
    assert _switches(settings) == {"priors": "auto", "depth": True, "normal": True, "consistency": False,
                                   "gpdfn": True}
    assert config_from_dict(ESGSConfig, settings).enabled  # a valid trainer config, not the baseline


def test_the_demo_computes_auto_priors_with_the_priors_job(tmp_path, monkeypatch):
    from esgs.core.priors import job

    requested = []

    def compute(settings, progress):
        requested.append(settings)
        raise ConfigError("stop here")

    monkeypatch.setattr(job, "compute_priors", compute)
    with pytest.raises(ConfigError, match="stop here"):
        demo.make_priors(DemoConfig(out=tmp_path), tmp_path / "scene", lambda event: None)
    assert [(s.scene, s.method, s.force) for s in requested] == [(tmp_path / "scene", "auto", False)]


def test_the_report_says_what_the_auto_priors_were_made_of(tmp_path):
    assert report._auto_priors_paragraph(tmp_path).startswith("The `auto` priors fuse")  # none written yet
    summary = {"views": 10, "labels_share": 0.7, "ndn_share": 0.2, "sfm_share": 0.01, "sky_share": 0.05,
               "labels_error": 0.02, "ndn_error": 0.08, "labels_views_used": 9, "ndn_views_used": 10,
               "coverage": 0.91, "mean_confidence": 0.6}
    folder = tmp_path / "priors" / "auto"
    folder.mkdir(parents=True)
    (folder / "auto.json").write_text(json.dumps({"summary": summary, "sources_used": ["sfm", "labels"],
                                                  "skipped": {"ndn": "ndn priors failed: no weights"}}))
    text = report._auto_priors_paragraph(tmp_path)
    assert "Here: 91% of pixels (labels 70%, ndn 20%, sfm 1%), mean confidence 0.60, sky 5%" in text
    assert "Left out: ndn (ndn priors failed: no weights)." in text and "NDN:" not in text


def test_each_prior_source_drives_the_losses_its_maps_support():
    # sfm has sparse depth only: consistency stands in for the missing normals
    assert _switches(esgs_settings("sfm")) == {"priors": "sfm", "depth": True, "normal": False, "consistency": True,
                                               "gpdfn": True}
    assert _switches(esgs_settings("gt", gpdfn=False)) == {"priors": "gt", "depth": True, "normal": True,
                                                           "consistency": False, "gpdfn": False}
    assert esgs_settings("ndn") == config_to_dict(full_esgs("ndn"))
    with pytest.raises(ConfigError, match="labels"):
        esgs_settings("labels")
    with pytest.raises(ConfigError, match="priors"):
        DemoConfig(priors="mvs").validate()


def test_sparse_points_setting_is_checked():
    with pytest.raises(ConfigError, match="sparse_points must be one of triangulated, exact"):
        DemoConfig(sparse_points="lidar").validate()
    assert DemoConfig().sparse_points == "triangulated"


def test_the_command_line_offers_exactly_the_demo_prior_sources():
    result = subprocess.run([sys.executable, "-m", "esgs.core", "demo", "--priors", "labels", "--out", "unused"],
                            capture_output=True, text=True)
    assert result.returncode == 2 and "invalid choice: 'labels'" in result.stderr
    assert "ndn, sfm, auto, gt" in result.stderr or "'ndn', 'sfm', 'auto', 'gt'" in result.stderr


def _saved_config(config: DemoConfig, priors: str, **changes) -> dict:
    """The config.json the demo's ESGS run with ``priors`` writes today, with ``changes``."""
    from esgs.core.train import TrainConfig

    train = TrainConfig(iterations=config.iterations, max_gaussians=config.max_gaussians, method="esgs",
                        method_config=demo._esgs_settings_of(esgs_settings(priors)))
    return {**config_to_dict(train), **changes}


def test_a_run_folder_from_other_settings_is_neither_reused_nor_resumed(tmp_path):
    config = DemoConfig(out=tmp_path, priors="ndn", iterations=1500)
    run = tmp_path / "runs" / "esgs"
    run.mkdir(parents=True)
    (run / "train_result.json").write_text(json.dumps({"status": "completed"}))
    (run / "metrics.json").write_text("{}")

    def attempt(saved: dict, demo_config: DemoConfig = config, events=None):
        (run / "config.json").write_text(json.dumps(saved))
        return demo.train_method(demo_config, tmp_path / "scene", "esgs", esgs_settings("ndn"),
                                 (events.append if events is not None else lambda event: None), snapshots=False)

    # other priors: the method's settings compared key by key
    with pytest.raises(ConfigError, match=r"normal False -> True") as error:
        attempt(_saved_config(config, "sfm"))
    assert "'sfm' -> 'ndn'" in str(error.value) and "another --out" in str(error.value)
    # a run from before the sky model, in the layout of its time (it trained without one)
    legacy = {"iterations": 1500, "max_gaussians": config.max_gaussians, "esgs": esgs_settings("ndn")}
    with pytest.raises(ConfigError, match="sky 'none' -> 'envmap'"):
        attempt(legacy)
    # a run from before a default changed: hidden Gaussians were not pruned then
    predating = _saved_config(config, "ndn")
    del predating["prune_hidden"]
    with pytest.raises(ConfigError, match=r"prune_hidden 0.0 -> 0.1"):
        attempt(predating)
    # a run from before the normal prior met each pixel's surface Gaussian
    predating = _saved_config(config, "ndn")
    del predating["method_config"]["normal_render"]
    with pytest.raises(ConfigError, match=r"normal_render 'composited' -> 'thin'"):
        attempt(predating)
    # a run from before GPDFN's width became 8 (its saved settings lack the key only in tests:
    # every run since the setting existed saved it)
    predating = _saved_config(config, "ndn")
    del predating["method_config"]["gpdfn_hidden"]
    with pytest.raises(ConfigError, match=r"gpdfn_hidden 16 -> 8"):
        attempt(predating)
    # the same settings are reused (no training: the scene does not even exist)
    events = []
    summary = attempt(_saved_config(config, "ndn"), events=events)
    assert summary["status"] == "completed" and "reusing finished run" in events[0].message
    with pytest.raises(ConfigError, match="iterations 1500 -> 300"):
        attempt(_saved_config(config, "ndn"), DemoConfig(out=tmp_path, iterations=300))


# --- the report's geometry pictures and scores -----------------------------------------
def _plane_depth(height: int, width: int, focal: float) -> np.ndarray:
    """z depth [H, W] of a plane tilted toward a camera at the origin (about 3 to 6 units)."""
    v, u = np.mgrid[0:height, 0:width] + 0.5
    rays = np.stack([(u - width / 2) / focal, (v - height / 2) / focal, np.ones_like(u)], axis=-1)
    normal = np.array([0.0, -0.6, -0.8])
    return (-4.0 / (rays @ normal)).astype(np.float32)


def test_geometry_scores_align_relative_depth_and_measure_normal_angles():
    truth = _plane_depth(30, 40, 30.0)
    mask = np.ones(truth.shape, bool)
    up = np.broadcast_to(np.array([0.0, -1.0, 0.0], np.float32), (*truth.shape, 3))
    # an affine copy of the truth (what a relative prior is) scores perfectly after the fit
    exact = report.geometry_scores(0.25 * truth + 3.0, up, mask, truth, up, mask)
    assert exact["abs_rel"] == pytest.approx(0.0, abs=1e-4) and exact["delta1"] == 1.0
    assert exact["normal_mean_deg"] == pytest.approx(0.0, abs=0.1) and exact["normal_within_11_25"] == 1.0
    assert exact["pixels"] == truth.size
    # normals tilted by 30 degrees, depth 10 % too deep on half the view
    tilted = np.broadcast_to(np.array([0.0, -math.cos(math.radians(30)), math.sin(math.radians(30))], np.float32),
                             up.shape)
    wrong = truth.copy()
    wrong[:, :20] *= 1.1
    scores = report.geometry_scores(wrong, tilted, mask, truth, up, mask)
    assert scores["normal_mean_deg"] == pytest.approx(30.0, abs=0.1) and scores["normal_within_11_25"] == 0.0
    assert 0.005 < scores["abs_rel"] < 0.1
    # only pixels where the map has values count; no normals -> no normal scores
    sparse = np.zeros_like(mask)
    sparse[::5, ::5] = True
    only_depth = report.geometry_scores(np.where(sparse, truth, 0), None, sparse, truth, up, mask)
    assert only_depth["pixels"] == int(sparse.sum()) and "normal_mean_deg" not in only_depth


def test_a_relative_prior_is_drawn_aligned_to_the_rendered_depth():
    rendered = _plane_depth(30, 40, 30.0)
    valid = np.ones(rendered.shape, bool)
    normals = np.broadcast_to(np.array([0.0, -0.6, -0.8], np.float32), (*rendered.shape, 3)).copy()
    relative = PriorMaps(depth=(rendered - 2.0) / 5.0, normal=normals, mask=valid, relative_depth=True, source="ndn")
    limits = (float(rendered.min()), float(rendered.max()))
    config = DemoConfig(priors="ndn")
    depth_panel, normal_panel = report._prior_panels(config, relative, rendered, valid, limits)
    strip = 18  # the caption
    expected = report.colorize_depth(rendered, valid, limits)
    assert np.abs(depth_panel[strip:].astype(int) - expected.astype(int)).max() <= 3
    assert np.array_equal(normal_panel[strip:], report.colorize_normals(normals, valid))
    # drawn without the fit, [0.1, 0.8] relative values would all clip to the far colour
    raw = report.colorize_depth(relative.depth, valid, limits)
    assert np.abs(raw.astype(int) - expected.astype(int)).max() > 50


def test_sparse_prior_samples_are_dilated_to_be_seen():
    rendered = _plane_depth(30, 40, 30.0)
    mask = np.zeros(rendered.shape, bool)
    mask[5::10, 5::10] = True
    sparse = PriorMaps(depth=np.where(mask, rendered, 0).astype(np.float32), normal=None, mask=mask,
                       relative_depth=False, source="sfm")
    (panel,) = report._prior_panels(DemoConfig(priors="sfm"), sparse, rendered, np.ones_like(mask),
                                    (float(rendered.min()), float(rendered.max())))
    coloured = panel[18:].any(axis=-1)
    assert coloured.sum() == 9 * mask.sum()


# --- the priors stage with the shipped NDN weights, and the report's geometry figure ---
def _add_ground_truth(scene):
    """priors/gt of the training-test scene: its ground plane z = 0 seen from every camera."""
    from esgs.core.colmap import read_model

    model = read_model(scene / "sparse" / "0")
    camera = model.cameras[1]
    fx, fy, cx, cy = camera.params
    v, u = np.mgrid[0:camera.height, 0:camera.width] + 0.5
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1)  # camera frame, z = 1
    for image in model.images.values():
        rotation = image.rotation_matrix()
        centre = image.camera_center()
        world_rays = rays @ rotation  # R^T r for every pixel
        depth = (-centre[2] / world_rays[..., 2]).astype(np.float32)  # z depth: rays have camera z = 1
        normal = np.broadcast_to(rotation @ np.array([0.0, 0.0, 1.0]), depth.shape + (3,)).astype(np.float32)
        mask = depth > 0
        write_prior_maps(scene, "gt", image.name, depth=np.where(mask, depth, 0), normal=normal, mask=mask)


@pytest.fixture(scope="module")
def ndn_scene(tmp_path_factory):
    """A 3-view plane scene (the fewest NDN's view triples need) with exact gt maps and NDN
    priors from the shipped weights (~2 CPU seconds per view)."""
    scene = make_scene(tmp_path_factory.mktemp("demo") / "scene", views=3, width=64, height=48)
    _add_ground_truth(scene)
    events = []
    demo.make_priors(DemoConfig(out=scene.parent, priors="ndn"), scene, events.append)
    return scene, events


def test_ndn_priors_come_from_the_shipped_weights_and_are_reused(ndn_scene):
    scene, events = ndn_scene
    assert events[-1].stage == "ndn priors" and events[-1].kind == "done" and events[-1].total == 3
    for index in range(3):
        maps = load_prior_maps(scene, "ndn", f"view_{index:03d}.png")
        assert maps.relative_depth and maps.depth.shape == (48, 64) and maps.normal.shape == (48, 64, 3)
        lengths = np.linalg.norm(maps.normal[maps.mask], axis=-1)
        assert maps.mask.any() and np.allclose(lengths, 1.0, atol=1e-3)
    # the plane is seen from above: the predicted normals face the cameras (negative z)
    assert np.mean(maps.normal[maps.mask][:, 2]) < 0
    assert report._ndn_weights(scene).startswith("the depth network shipped in the package")
    assert "normals from the shipped completion network" in report._ndn_weights(scene)
    again = []
    demo.make_priors(DemoConfig(out=scene.parent, priors="ndn"), scene, again.append)
    assert [e.kind for e in again] == ["message"] and "reusing" in again[0].message


def test_a_missing_prior_source_is_a_clear_error(ndn_scene, tmp_path):
    scene, _ = ndn_scene
    bare = make_scene(tmp_path / "bare", views=3, width=32, height=24)
    with pytest.raises(ConfigError, match="'gt' priors"):
        demo.make_priors(DemoConfig(out=tmp_path, priors="gt"), bare, lambda event: None)


def test_the_report_shows_ndn_depth_and_normal_priors_beside_the_rendering(ndn_scene, tmp_path):
    scene, _ = ndn_scene
    config = DemoConfig(out=tmp_path / "demo", priors="ndn", iterations=30, max_gaussians=2000, width=64, height=48)
    result = demo.train_method(config, scene, "esgs", esgs_settings("ndn"), lambda event: None, snapshots=False)
    assert result["status"] == "completed"
    saved = json.loads((config.out / "runs" / "esgs" / "config.json").read_text())["method_config"]
    assert saved["priors"] == "ndn" and saved["depth"] and saved["normal"]
    (config.out / "report").mkdir(parents=True)
    name, scores = report._geometry_figure(config, scene, config.out / "report")
    picture = report.read_image(config.out / "report" / name)
    assert picture.shape[0] == 3 * (48 + 18) + 2 * 4  # truth, the ndn priors, the rendering
    assert picture.shape[1] == 3 * 64 + 2 * 4  # image, depth, normals
    assert set(scores) == {"`ndn` prior", "ESGS rendering"}
    for row in scores.values():
        assert 0 <= row["abs_rel"] < 1 and 0 <= row["delta1"] <= 1 and 0 <= row["normal_mean_deg"] <= 180
    # the prior row is the NDN maps scored against the plane: recompute it independently
    from esgs.core.ndn.infer import score_view

    view = "view_000.png"
    prior = load_prior_maps(scene, "ndn", view)
    truth = load_prior_maps(scene, "gt", view)
    mask = prior.mask & truth.mask
    expected = score_view(prior.depth, np.moveaxis(prior.normal, -1, 0), truth.depth,
                          np.moveaxis(truth.normal, -1, 0), mask)
    assert scores["`ndn` prior"]["abs_rel"] == pytest.approx(expected["abs_rel"], abs=1e-6)
    assert scores["`ndn` prior"]["normal_mean_deg"] == pytest.approx(expected["normal_mean_deg"], abs=1e-4)


# --- the whole chain -----------------------------------------------------------------------
@pytest.mark.slow
def test_tiny_demo_runs_every_stage_and_reuses_finished_work(tmp_path, monkeypatch):
    pytest.importorskip("bpy", reason="the demo's scene and Blender stages need the bpy module")
    measured = []
    original = demo.mesh_distances

    def counting(scene, run, *args, **kwargs):
        measured.append(run.name)
        return original(scene, run, *args, **kwargs)

    monkeypatch.setattr(demo, "mesh_distances", counting)
    events = []
    config = DemoConfig(out=tmp_path / "demo", views=4, width=96, height=54, samples=4, iterations=30,
                        snapshots=2, max_gaussians=4000)
    assert config.priors == "auto"
    report_path = demo.run_demo(config, progress=events.append)
    text = report_path.read_text()
    assert "| ESGS |" in text and "| 3DGS |" in text and "| `auto` prior |" in text
    assert "The `auto` priors fuse" in text and "depth network shipped in the package" in text
    assert "normals from the shipped completion network" in text
    # 4 renders of 96x54 give SIFT nothing to triangulate: the demo says so and keeps the exact points
    assert any("no SfM points could be triangulated" in (e.message or "") for e in events)
    assert "generator's exact surface samples" in text
    for name in ("curves.png", "geometry.png", "heat_map.png", "training_progress.png"):
        assert (tmp_path / "demo" / "report" / name).stat().st_size > 0, name
    assert (tmp_path / "demo" / "blender" / "results.blend").is_file()
    metrics = json.loads((tmp_path / "demo" / "runs" / "esgs" / "metrics.json").read_text())
    assert metrics["psnr"] > 8 and f"{metrics['psnr']:.2f}" in text
    saved = json.loads((tmp_path / "demo" / "runs" / "esgs" / "config.json").read_text())["method_config"]
    assert saved["depth"] and saved["normal"] and saved["gpdfn"] and saved["priors"] == "auto"
    assert saved["depth_weight"] == AUTO_DEPTH_WEIGHT
    # distances are measured once per run: Blender's comparison serves ESGS, core measures 3DGS
    assert measured == ["3dgs"]
    blender = json.loads((tmp_path / "demo" / "blender" / "compare.json").read_text())
    esgs_row = next(line for line in text.splitlines() if line.startswith("| ESGS |"))
    assert f"| {report._fmt(blender['gaussians_to_mesh_filtered']['mean'])} |" in esgs_row
    assert events[-1].kind == "done"
    # a second run reuses the scene, the priors and both finished runs
    again = []
    demo.run_demo(config, progress=again.append)
    messages = " ".join(e.message for e in again if e.kind == "message")
    assert "scene: reusing" in messages and "priors: reusing" in messages
    assert "esgs: reusing finished run" in messages and "3dgs: reusing finished run" in messages
