"""Training from Blender (esgs_addon/training_job.py, operators/train.py, the panels).

Headless (the bpy module, like ``blender -b``) the operator blocks until the trainer ends.
Most tests use a small fake trainer with the CLI's interface; the last one trains for real
when the engine's trainer is installed.
"""
from __future__ import annotations

import json
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from esgs.core.apps import jobs  # noqa: E402
from esgs.core.errors import DatasetError  # noqa: E402
from esgs.esgs_addon import compare_mesh, gaussians_import, training_job  # noqa: E402

FAKE_TRAINER = textwrap.dedent(
    """
    import argparse, json, sys, time
    from pathlib import Path
    import numpy as np
    from esgs.core.formats.ply import GaussianPly, write_gaussians_ply

    parser = argparse.ArgumentParser()
    parser.add_argument("job")
    parser.add_argument("config")
    parser.add_argument("--events", required=True)
    parser.add_argument("--result", required=True)
    parser.add_argument("--stop-file", required=True)
    parser.add_argument("--crash", action="store_true")
    parser.add_argument("--evaluate", action="store_true")
    args = parser.parse_args()
    config = json.loads(Path(args.config).read_text())
    iterations = config["iterations"]
    out = Path(config["out"])
    out.mkdir(parents=True, exist_ok=True)
    (out / "child_config.json").write_text(json.dumps(config))
    with open(args.events, "a") as events:
        for step in range(1, iterations + 1):
            events.write(json.dumps({"step": step, "total": iterations, "stage": "train",
                                     "metrics": {"loss": 1.0 / step, "psnr": 20.0 + step, "n_gaussians": 16},
                                     "kind": "progress"}) + "\\n")
            events.flush()
    if args.crash:
        sys.exit("RuntimeError: the fake trainer ran out of memory")
    # 16 Gaussians on the plane z = 0.01, opaque
    u = np.linspace(-0.75, 0.75, 4)
    x, y = np.meshgrid(u, u)
    means = np.column_stack([x.ravel(), y.ravel(), np.full(16, 0.01)])
    write_gaussians_ply(out / "point_cloud.ply", GaussianPly(
        means=means, normals=np.zeros((16, 3)), sh_dc=np.zeros((16, 3)), sh_rest=np.zeros((16, 0, 3)),
        opacity_logit=np.full(16, 3.0), log_scales=np.full((16, 3), -3.0), quats_wxyz=np.tile([1.0, 0, 0, 0], (16, 1))))
    done = {"n_gaussians": 16}
    if args.evaluate:
        # like the real trainer: held-out metrics in metrics.json and in the done event
        (out / "config.json").write_text(json.dumps(config))
        (out / "metrics.json").write_text(json.dumps({"split": "test", "views_count": 2, "psnr": 12.5, "ssim": 0.4,
                                                      "lpips": 0.5, "views": []}))
        with open(args.events, "a") as events:
            events.write(json.dumps({"step": 2, "total": 2, "stage": "eval", "metrics": {"psnr": 12.5},
                                     "kind": "progress"}) + "\\n")
        done.update(psnr=12.5, ssim=0.4, lpips=0.5)
    with open(args.events, "a") as events:
        events.write(json.dumps({"step": iterations, "total": iterations, "stage": "train",
                                 "metrics": done, "kind": "done", "message": "completed"}) + "\\n")
    """
)


@pytest.fixture
def fake_trainer(tmp_path, monkeypatch):
    script = tmp_path / "fake_trainer.py"
    script.write_text(FAKE_TRAINER)
    monkeypatch.setattr(training_job, "TRAINER_OVERRIDE", [sys.executable, str(script)])
    return script


@pytest.fixture
def scene_dir(tmp_path) -> Path:
    """A scene folder as the trainer reads it: images/ and a COLMAP model in sparse/0."""
    from tests.blender.colmap_helpers import synthetic_model, write_scene

    return write_scene(tmp_path, synthetic_model(), name="scene")


def colmap_collection(folder: Path, name: str = "scene"):
    """A collection tagged like the COLMAP import tags it."""
    collection = bpy.data.collections.new(name)
    bpy.context.scene.collection.children.link(collection)
    collection[training_job.PROP_COLMAP_SOURCE] = str(folder / "sparse" / "0")
    return collection


def plane_mesh(name: str = "ground truth"):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], [], [(0, 1, 2), (0, 2, 3)])
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def test_headless_operator_trains_imports_and_compares(tmp_path, fake_trainer, scene_dir):
    assert bpy.app.background  # the blocking path is the one under test
    collection = colmap_collection(scene_dir)
    placement = np.eye(4)
    placement[:3, 3] = (0.0, 0.0, 5.0)  # the COLMAP import re-oriented the scene: the result must follow
    collection[training_job.PROP_COLMAP_TRANSFORM] = placement.ravel().tolist()
    settings = bpy.context.scene.esgs.training
    settings.iterations = 12
    settings.run_dir = str(tmp_path / "run")

    assert bpy.ops.esgs.train() == {"FINISHED"}
    assert settings.status == "finished"
    assert (settings.step, settings.total) == (12, 12)
    assert settings.psnr == pytest.approx(32.0)
    assert settings.last_run_dir == str(tmp_path / "run")
    config = json.loads((tmp_path / "run" / "child_config.json").read_text())
    assert (config["scene"], config["out"]) == (str(scene_dir), str(tmp_path / "run")) and "iterations" in config

    obj = bpy.context.view_layer.objects.active
    assert gaussians_import.is_gaussian_object(obj)
    assert obj.name in collection.objects
    assert obj[training_job.PROP_RUN_DIR] == str(tmp_path / "run")
    np.testing.assert_allclose(np.array(obj.matrix_world), placement)

    plane = plane_mesh()
    plane.location = (0.0, 0.0, 5.0)
    bpy.context.view_layer.update()
    summary = compare_mesh.compare_to_mesh(obj, plane, threshold_m=0.05, n_surface_samples=2000)
    assert summary["gaussians_to_mesh"]["mean"] == pytest.approx(0.01, abs=1e-5)
    assert summary["precision"] == 1.0


def test_failure_shows_the_trainers_message(tmp_path, fake_trainer, scene_dir, monkeypatch):
    monkeypatch.setattr(training_job, "TRAINER_OVERRIDE", list(training_job.TRAINER_OVERRIDE) + ["--crash"])
    settings = bpy.context.scene.esgs.training
    settings.scene_dir = str(scene_dir)
    settings.run_dir = str(tmp_path / "run")
    settings.iterations = 3
    settings.depth = True
    settings.priors = "gt"
    (scene_dir / "priors" / "gt" / "depth").mkdir(parents=True)
    objects_before = len(bpy.data.objects)
    with pytest.raises(RuntimeError, match="ran out of memory"):
        bpy.ops.esgs.train()
    config = json.loads((tmp_path / "run" / "child_config.json").read_text())
    assert config["method"] == "esgs"  # the ESGS switches reach the trainer as its TrainConfig
    assert config["method_config"]["depth"] is True and config["method_config"]["priors"] == "gt"
    assert settings.status == "failed"
    assert settings.error == "RuntimeError: the fake trainer ran out of memory"
    assert len(bpy.data.objects) == objects_before
    # the failed run can be resumed: same folders, --resume
    monkeypatch.setattr(training_job, "TRAINER_OVERRIDE", list(training_job.TRAINER_OVERRIDE)[:-1])
    assert bpy.ops.esgs.train_resume() == {"FINISHED"}
    config = json.loads((tmp_path / "run" / "child_config.json").read_text())
    assert config["resume"] is True
    assert "method_config" not in config and "priors" not in config  # the run keeps its saved options
    assert settings.status == "finished"


def test_no_scene_folder_is_a_clear_error():
    with pytest.raises(RuntimeError, match="no scene folder"):
        bpy.ops.esgs.train()
    with pytest.raises(RuntimeError, match="no earlier run"):
        bpy.ops.esgs.train_resume()


def test_a_folder_that_is_not_a_scene_fails_before_any_run_folder(tmp_path, fake_trainer):
    not_a_scene = tmp_path / "photos"
    (not_a_scene / "images").mkdir(parents=True)
    settings = bpy.context.scene.esgs.training
    settings.scene_dir = str(not_a_scene)
    for run_dir in (str(tmp_path / "run"), ""):  # a named run folder, and a new one in the runs folder
        settings.run_dir = run_dir
        with pytest.raises(RuntimeError, match="not a scene folder: no COLMAP model") as raised:
            bpy.ops.esgs.train()
        assert "Scene folder" in str(raised.value) and "--" not in str(raised.value)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["fake_trainer.py", "photos"]  # no run folder
    assert settings.status == "" and settings.last_run_dir == ""


def test_missing_priors_and_a_used_run_folder_are_said_in_panel_words(tmp_path, fake_trainer, scene_dir):
    settings = bpy.context.scene.esgs.training
    settings.scene_dir, settings.run_dir, settings.method = str(scene_dir), str(tmp_path / "run"), "esgs"
    settings.prior_source = "ndn"  # offered although not computed yet: it is what Compute Priors makes
    assert settings.priors == "ndn" and bpy.context.scene.esgs.priors.method == "ndn"
    with pytest.raises(RuntimeError, match="no ndn priors.*press Compute Priors with ndn") as raised:
        bpy.ops.esgs.train()
    assert "--" not in str(raised.value) and not (tmp_path / "run").exists()

    assert settings.depth and settings.normal  # choosing the source gave the full method
    settings.prior_source = "NONE"  # its prior losses stay on, without a source now
    with pytest.raises(RuntimeError, match="choose a Prior source in the Training section") as raised:
        bpy.ops.esgs.train()
    assert "--" not in str(raised.value) and not (tmp_path / "run").exists()

    settings.depth = settings.normal = False
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.json").write_text("{}")  # a run the trainer wrote
    with pytest.raises(RuntimeError, match="already holds a run.*Resume Training"):
        bpy.ops.esgs.train()


def test_esgs_on_auto_priors_not_made_yet_starts_and_says_it_makes_them_first(tmp_path, fake_trainer, scene_dir):
    from esgs.core.methods import full_esgs
    from esgs.panels.training_panel import ESGS_PT_training

    settings = bpy.context.scene.esgs.training
    settings.scene_dir, settings.run_dir, settings.iterations = str(scene_dir), str(tmp_path / "run"), 3
    settings.method = "esgs"  # the full method on auto, the default source
    assert not (scene_dir / "priors" / "auto").exists()
    config = training_job.training_config(settings)
    assert config.method_config == full_esgs("auto")
    training_job.check_scene(scene_dir, config, tmp_path / "run")  # not refused: the run makes them
    assert training_job.priors_made_first(scene_dir, config) == "auto"

    # while the child computes them (no step yet) the panel says so
    training_job.copy_state(settings, jobs.JobState(status="running", step=0, total=3))
    settings.last_scene_dir = str(scene_dir)
    labels = [entry[1] for entry in draw_panel(ESGS_PT_training) if entry[0] == "label"]
    assert "Computing auto priors before the first step" in labels
    settings.status = ""

    assert bpy.ops.esgs.train() == {"FINISHED"}
    sent = json.loads((tmp_path / "run" / "child_config.json").read_text())
    assert sent["method"] == "esgs" and sent["method_config"]["priors"] == "auto"
    assert sent["method_config"]["depth_weight"] == full_esgs("auto").depth_weight

    # other sources are still refused at once; auto priors already there are not made again
    (scene_dir / "priors" / "auto" / "depth").mkdir(parents=True)
    assert training_job.priors_made_first(scene_dir, config) is None
    settings.prior_source = "ndn"
    with pytest.raises(DatasetError, match="no ndn priors"):
        training_job.check_scene(scene_dir, training_job.training_config(settings))


def test_scene_folder_from_the_imported_collection(scene_dir, tmp_path):
    with pytest.raises(DatasetError):
        training_job.find_scene_dir(bpy.context.scene)
    colmap_collection(scene_dir)
    assert training_job.find_scene_dir(bpy.context.scene) == scene_dir
    other = tmp_path / "other"
    other.mkdir()
    assert training_job.find_scene_dir(bpy.context.scene, str(other)) == other
    with pytest.raises(DatasetError, match="does not exist"):
        training_job.find_scene_dir(bpy.context.scene, str(tmp_path / "missing"))
    tagged = bpy.data.collections.new("tagged")
    tagged[training_job.PROP_SCENE_DIR] = str(other)
    assert training_job.scene_dir_of_collection(tagged) == other


def test_panel_settings_become_a_train_config():
    settings = bpy.context.scene.esgs.training
    settings.depth, settings.gpdfn, settings.priors, settings.width = True, True, "gt", 480
    config = training_job.training_config(settings)
    assert (config.method, config.width) == ("esgs", 480)
    assert (config.method_config.depth, config.method_config.gpdfn, config.method_config.priors) == (True, True, "gt")
    settings.depth, settings.normal, settings.consistency, settings.gpdfn, settings.priors = False, False, False, False, ""
    assert training_job.training_config(settings).method == "3dgs"


def test_new_run_folders_do_not_collide(scene_dir):
    first = training_job.new_run_dir(scene_dir)
    first.mkdir(parents=True)
    second = training_job.new_run_dir(scene_dir)
    assert second != first and second.parent == first.parent == scene_dir.parent / "esgs_runs"


_ICONS = {item.identifier for item in bpy.types.UILayout.bl_rna.functions["label"].parameters["icon"].enum_items}


class _RecordingLayout:
    """Stands in for a UILayout: accepts every call, records the texts and properties shown."""

    def __init__(self, record: list):
        self.record = record

    def __getattr__(self, name):
        def call(*args, **kwargs):
            function = bpy.types.UILayout.bl_rna.functions[name]  # a real UILayout call...
            assert set(kwargs) <= {p.identifier for p in function.parameters}, (name, kwargs)  # ...with real keywords
            if "icon" in kwargs:
                assert kwargs["icon"] in _ICONS, kwargs["icon"]
            if name == "prop":
                data, prop = args[0], args[1]
                if not prop.startswith("["):
                    assert hasattr(data, prop), prop  # a misspelt property would show an error in Blender
                self.record.append(("prop", prop))
            elif name in ("label", "operator", "progress"):
                self.record.append((name, kwargs.get("text") or (args[0] if args else "")))
            return self

        return call

    def __setattr__(self, name, value):
        if name == "record":
            object.__setattr__(self, name, value)


def draw_panel(panel_class) -> list:
    record: list = []
    panel = type("PanelStandIn", (), {"layout": _RecordingLayout(record)})()
    panel_class.draw(panel, bpy.context)
    return record


def test_panels_draw_progress_and_results(tmp_path):
    from esgs.panels.results_panel import ESGS_PT_results
    from esgs.panels.training_panel import ESGS_PT_training

    settings = bpy.context.scene.esgs.training
    state = jobs.JobState(status="running", step=40, total=100, loss=0.05, psnr=21.5, n_gaussians=1234, eta_s=75)
    training_job.copy_state(settings, state)
    record = draw_panel(ESGS_PT_training)
    assert ("progress", "40 / 100") in record
    assert ("label", "Training PSNR (last views) 21.50 dB") in record and ("label", "ETA 1:15") in record
    assert ("operator", "esgs.train_cancel") in record

    training_job.copy_state(settings, jobs.JobState(status="failed", error="boom: out of memory"))
    settings.last_run_dir = str(tmp_path)
    record = draw_panel(ESGS_PT_training)
    assert ("operator", "esgs.train_resume") in record
    assert ("label", "boom: out of memory") in record

    from esgs.core.formats.ply import GaussianPly, write_gaussians_ply

    write_gaussians_ply(tmp_path / "g.ply", GaussianPly(
        means=np.array([[0.0, 0.0, 0.02]]), normals=np.zeros((1, 3)), sh_dc=np.zeros((1, 3)),
        sh_rest=np.zeros((1, 0, 3)), opacity_logit=np.ones(1), log_scales=np.zeros((1, 3)),
        quats_wxyz=np.array([[1.0, 0, 0, 0]])))
    obj = gaussians_import.import_gaussians(tmp_path / "g.ply")
    bpy.context.view_layer.objects.active = obj
    compare_mesh.compare_to_mesh(obj, plane_mesh(), n_surface_samples=200, threshold_m=0.05)
    record = draw_panel(ESGS_PT_results)
    labels = [text for kind, text in record if kind == "label"]
    assert "mean 0.02" in labels
    assert any(text.startswith("At 0.05 m: precision 1.000") for text in labels)
    assert "Recall over the whole mesh (no training cameras known)" in labels
    assert sum(1 for kind, text in record if kind == "prop" and text.startswith('["')) == 8  # display + heat map

    # every Gaussian below the opacity filter: the scores are undefined, and the panel says why
    summary = compare_mesh.compare_to_mesh(obj, plane_mesh(), opacity_min=0.99, n_surface_samples=200, threshold_m=0.05)
    assert summary["precision"] is None and summary["fscore"] is None
    assert "lower the opacity filter" in compare_mesh.describe(summary)
    labels = [text for kind, text in draw_panel(ESGS_PT_results) if kind == "label"]
    assert "No Gaussian at opacity >= 0.99: scores undefined, lower the opacity filter" in labels
    assert not any(text.startswith("At 0.05 m: precision") for text in labels)


@pytest.mark.slow
def test_real_trainer_end_to_end(tmp_path):
    """The installed trainer on a tiny synthetic plane scene: train headless, import, compare."""
    if not jobs.trainer_available():
        pytest.skip("the engine's trainer (esgs.core.train) is not installed")
    pytest.importorskip("torch")
    from tests.core.train.scene import make_scene

    scene = make_scene(tmp_path / "scene", views=6, width=32, height=24)
    settings = bpy.context.scene.esgs.training
    settings.scene_dir = str(scene)
    settings.run_dir = str(tmp_path / "run")
    settings.iterations = 20
    settings.width = 32
    assert bpy.ops.esgs.train() == {"FINISHED"}, settings.error
    assert settings.status == "finished"
    assert (tmp_path / "run" / "point_cloud.ply").is_file()
    obj = bpy.context.view_layer.objects.active
    assert gaussians_import.is_gaussian_object(obj) and len(obj.data.points) > 0
    # the scene's ground truth is the plane z = 0 over [-1, 1]^2
    big = bpy.data.meshes.new("plane")
    big.from_pydata([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], [], [(0, 1, 2), (0, 2, 3)])
    plane = bpy.data.objects.new("plane", big)
    bpy.context.scene.collection.objects.link(plane)
    summary = compare_mesh.compare_to_mesh(obj, plane, opacity_min=0.0, threshold_m=0.1, n_surface_samples=2000)
    assert summary["n_gaussians"] == len(obj.data.points)
    assert 0.0 <= summary["gaussians_to_mesh"]["median"] < 1.0


def test_ui_polling_updates_settings_and_imports(tmp_path, fake_trainer, scene_dir, monkeypatch):
    """The timer path of the UI, driven by hand (timers never fire in background mode)."""
    registered = []
    monkeypatch.setattr(bpy.app.timers, "register", lambda function, **kwargs: registered.append(function))
    job = training_job.start_training(scene_dir, tmp_path / "run", 5)
    training_job.start_polling(bpy.context.scene.name, training_job.job_key(scene_dir))
    assert len(registered) == 1
    poll = registered[0]
    settings = bpy.context.scene.esgs.training
    for _ in range(600):
        if poll() is None:
            break
        assert settings.status in ("running", "finished")
        import time

        time.sleep(0.05)
    else:
        pytest.fail("the job did not end")
    assert job.state().status == "finished"
    assert (settings.status, settings.step, settings.progress) == ("finished", 5, 1.0)
    imported = [obj for obj in bpy.data.objects if obj.get(training_job.PROP_RUN_DIR) == str(tmp_path / "run")]
    assert len(imported) == 1 and len(imported[0].data.points) == 16


def test_preferences_are_keyed_by_the_root_package(tmp_path, monkeypatch):
    from types import SimpleNamespace

    from esgs.esgs_addon import preferences

    assert preferences.ADDON_ID == "esgs"  # "bl_ext.<repository>.esgs" inside Blender
    assert preferences.ESGS_AP_preferences.bl_idname == preferences.ADDON_ID
    assert preferences.ESGS_AP_preferences.is_registered
    # registered without being enabled (the bpy module): defaults apply
    assert preferences.get_preferences() is None
    assert preferences.trainer_python() == jobs.find_python()
    assert preferences.trainer_threads() == 0
    python = tmp_path / "python"
    python.write_text("")
    fake = SimpleNamespace(python_path=str(python), threads=3, output_dir=str(tmp_path / "runs"))
    monkeypatch.setattr(preferences, "get_preferences", lambda context=None: fake)
    assert preferences.trainer_python() == str(python)
    assert preferences.trainer_threads() == 3
    assert preferences.runs_folder(tmp_path / "scene") == tmp_path / "runs"
    fake.python_path = str(tmp_path / "missing")
    with pytest.raises(Exception, match="does not exist"):
        preferences.trainer_python()


def test_a_finished_run_reports_and_shows_held_out_figures_apart_from_training_psnr(tmp_path, fake_trainer, scene_dir,
                                                                                   monkeypatch, capfd):
    from tests.blender.panel_drawing import draw_panel

    monkeypatch.setattr(training_job, "TRAINER_OVERRIDE", list(training_job.TRAINER_OVERRIDE) + ["--evaluate"])
    settings = bpy.context.scene.esgs.training
    settings.scene_dir = str(scene_dir)
    settings.run_dir = str(tmp_path / "run")
    settings.iterations = 5
    capfd.readouterr()
    assert bpy.ops.esgs.train() == {"FINISHED"}
    printed = capfd.readouterr()
    output = printed.out + printed.err
    # the last console line and the operator's report name each PSNR for what it measures
    assert "training PSNR (last views) 25.00 dB" in output
    assert "held-out PSNR 12.50 dB, SSIM 0.400, LPIPS 0.500 (2 views)" in output
    assert "training PSNR (last views) 12.50" not in output

    _, calls = draw_panel(bpy.types.ESGS_PT_training)
    labels = [call.text for call in calls if call.name == "label"]
    assert "Held-out views (2 not trained on)" in labels
    assert {"Held-out PSNR 12.50 dB", "Held-out SSIM 0.400", "Held-out LPIPS 0.500"} <= set(labels)
    assert "Training PSNR (last views): 25.00 dB" in labels
    assert not any(label.startswith("Mean ") for label in labels)  # no comparison yet

    # after Compare to Mesh on the imported result, its distances join the figures
    obj = bpy.context.view_layer.objects.active
    summary = compare_mesh.compare_to_mesh(obj, plane_mesh(), threshold_m=0.05, n_surface_samples=500, cameras=None)
    _, calls = draw_panel(bpy.types.ESGS_PT_training)
    labels = [call.text for call in calls if call.name == "label"]
    mean = summary["gaussians_to_mesh_filtered"]["mean"]
    assert f"Mean {mean:.3g} m" in labels and f"F-score {summary['fscore']:.3f}" in labels

