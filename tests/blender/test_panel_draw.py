"""Every panel of the add-on and its preferences draw without an error, in the checkout
(package ``esgs``) and as an installed extension (``bl_ext.user_default.esgs``), in the
states a user meets: nothing chosen yet, a scene folder chosen, jobs running, a run failed.

Drawing uses :class:`~tests.blender.panel_drawing.RecordingLayout` (every ``layout.*`` call
checked against the real UILayout and recorded), so no window is needed.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import esgs  # noqa: E402
from esgs.core.apps import jobs  # noqa: E402
from esgs.esgs_addon import gaussians_import, training_job  # noqa: E402
from tests.blender import panel_drawing  # noqa: E402
from esgs.panels.training_panel import NO_SCENE  # noqa: E402
from tests.blender.panel_drawing import draw_everything, draw_panel  # noqa: E402

REPO_ROOT = Path(esgs.__file__).resolve().parent
NO_SCENE_HINT = NO_SCENE


def operators(calls) -> list[str]:
    return [call.text for call in calls if call.name == "operator"]


def labels(calls) -> list[str]:
    return [call.text for call in calls if call.name == "label"]


def props(calls) -> list[str]:
    return [call.text for call in calls if call.name == "prop"]


@pytest.fixture
def scene_folder(tmp_path) -> Path:
    folder = tmp_path / "scene"
    (folder / "sparse" / "0").mkdir(parents=True)
    (folder / "images").mkdir()
    (folder / "priors" / "gt" / "depth").mkdir(parents=True)
    return folder


def test_every_panel_is_drawn():
    drawn = draw_everything(esgs)
    registered = {name for name in dir(bpy.types) if name.startswith("ESGS_PT_")}
    assert registered and set(drawn) == registered | {"preferences"}
    assert all(drawn.values()), [name for name, calls in drawn.items() if not calls]


def test_nothing_chosen_yet():
    drawn = draw_everything(esgs)
    assert labels(drawn["ESGS_PT_main"]) == [f"ESGS for Blender {esgs.__version__}"]
    assert {"esgs.generate_terrain", "esgs.render_dataset"} <= set(operators(drawn["ESGS_PT_terrain"]))
    assert {"esgs.import_colmap", "esgs.export_colmap"} <= set(operators(drawn["ESGS_PT_import"]))
    training = drawn["ESGS_PT_training"]
    assert {"esgs.train", "esgs.compute_priors"} <= set(operators(training))
    assert "esgs.train_cancel" not in operators(training) and "esgs.train_resume" not in operators(training)
    assert NO_SCENE_HINT in labels(training)
    assert {"scene_dir", "run_dir", "method", "iterations"} <= set(props(training))
    assert "esgs.import_gaussians" in operators(drawn["ESGS_PT_results"])
    assert "esgs.render_labels" in operators(drawn["ESGS_PT_labels"])
    assert {"python_path", "threads", "output_dir", "torch_variant", "wheel_dir"} <= set(props(drawn["preferences"]))
    assert {"esgs.trainer_setup", "esgs.trainer_check", "esgs.trainer_remove"} <= set(operators(drawn["preferences"]))


def test_a_scene_folder_chosen(scene_folder):
    bpy.context.scene.esgs.training.scene_dir = str(scene_folder)
    training = draw_everything(esgs)["ESGS_PT_training"]
    assert NO_SCENE_HINT not in labels(training)
    assert "esgs.train" in operators(training)


def test_esgs_method_jobs_running_and_a_failed_run(scene_folder, tmp_path):
    settings = bpy.context.scene.esgs
    settings.training.scene_dir = str(scene_folder)
    settings.training.method = "esgs"
    training = draw_everything(esgs)["ESGS_PT_training"]
    assert {"depth", "normal", "gpdfn"} <= set(props(training))

    training_job.copy_state(settings.training, jobs.JobState(status="running", step=3, total=10, loss=0.5,
                                                             psnr=20.0, n_gaussians=100, eta_s=9.0))
    settings.priors.status, settings.priors.total = "running", 4
    training = draw_everything(esgs)["ESGS_PT_training"]
    assert "esgs.train_cancel" in operators(training) and "esgs.compute_priors_cancel" in operators(training)
    assert "esgs.train" not in operators(training)

    training_job.copy_state(settings.training, jobs.JobState(status="failed", error="RuntimeError: " + "x" * 120))
    settings.training.last_run_dir = str(tmp_path / "run")
    settings.priors.status, settings.priors.last_method = "finished", "ndn"
    training = draw_everything(esgs)["ESGS_PT_training"]
    assert {"esgs.train", "esgs.train_resume"} <= set(operators(training))
    assert "Last run: failed" in labels(training) and "Priors written: priors/ndn" in labels(training)


def test_progress_names_the_psnr_of_each_stage(scene_folder):
    settings = bpy.context.scene.esgs.training
    settings.scene_dir = str(scene_folder)
    training_job.copy_state(settings, jobs.JobState(status="running", step=3, total=10, stage="train", psnr=29.0))
    assert "Training PSNR (last views) 29.00 dB" in labels(draw_everything(esgs)["ESGS_PT_training"])
    # the evaluation after training renders the held-out views
    training_job.copy_state(settings, jobs.JobState(status="running", step=1, total=3, stage="eval", psnr=12.8))
    training = labels(draw_everything(esgs)["ESGS_PT_training"])
    assert "Held-out PSNR 12.80 dB" in training and not any(text.startswith("Training PSNR") for text in training)


def test_a_finished_run_without_held_out_views_says_so(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.json").write_text(json.dumps({"split": "train", "views_count": 4, "psnr": 30.0, "ssim": 0.9,
                                                  "lpips": None, "lpips_unavailable": "disabled"}))
    settings = bpy.context.scene.esgs.training
    training_job.copy_state(settings, jobs.JobState(status="finished", step=10, total=10))
    settings.last_run_dir = str(run)
    training = labels(draw_everything(esgs)["ESGS_PT_training"])
    assert "Training views (the scene has no held-out split)" in training
    assert "PSNR 30.00 dB" in training and "LPIPS n/a" in training
    assert not any(text.startswith("Held-out") for text in training)


def test_the_training_time_estimate_below_iterations(tmp_path, monkeypatch):
    """Below Iterations: the estimate of the run (the default figures, then this machine's
    finished run), ESGS's auto priors when they are still to be made, read from files once."""
    from esgs.core.apps import estimate
    from esgs.esgs_addon import preferences, training_estimate
    from tests.core.test_estimate import write_run, write_scene

    training_estimate.clear_cache()
    monkeypatch.setattr(preferences, "trainer_threads", lambda context=None: 2)
    reads = []
    scene_image_size = estimate.scene_image_size
    monkeypatch.setattr(estimate, "scene_image_size", lambda folder: reads.append(folder) or scene_image_size(folder))
    scene = write_scene(tmp_path / "scene", views=12, width=640, height=360)
    settings = bpy.context.scene.esgs.training
    settings.scene_dir, settings.iterations, settings.width = str(scene), 2000, 320

    def estimate_labels() -> list[str]:
        calls = draw_panel(bpy.types.ESGS_PT_training)[1]
        after = [call.text for call in calls[[call.text for call in calls].index("iterations") + 1:]]
        return after[:after.index("width")]  # what is drawn between Iterations and Image width

    # 3DGS at 320x180: 15 s + 2000 x 0.12 s + 2 held-out views x 0.5 s = 256 s
    assert estimate_labels() == ["≈ 4 min (typical 2-core laptop)"]
    assert estimate_labels() == ["≈ 4 min (typical 2-core laptop)"] and len(reads) == 1  # no file read at a redraw
    # ESGS on auto priors not made yet: 15 + 2000 x 0.20 + 1 = 416 s; the priors of 12 views of
    # 640x360: 10 s + 12 x (1.7 + 4.0 x 4) s = 222 s
    settings.method = "esgs"
    assert settings.priors == "auto"
    assert estimate_labels() == ["≈ 7 min (typical 2-core laptop)", "+ auto priors first, about 4 min"]
    # a run of this scene finished here at 0.1 s a step at 320x180 (ESGS): 15 + 200 + 1 s
    run = write_run(tmp_path / "esgs_runs" / "run", step_s=0.1, size=(320, 180), method="esgs", scene=str(scene))
    settings.status, settings.last_run_dir = "finished", str(run)
    assert estimate_labels()[0] == "≈ 4 min (measured here)"
    # a running job shows its ETA instead
    training_job.copy_state(settings, jobs.JobState(status="running", step=3, total=10, eta_s=9.0))
    assert estimate_labels() == []


def test_the_gaussians_panel_with_gaussians_selected(tmp_path):
    from esgs.core.formats.ply import GaussianPly, write_gaussians_ply

    write_gaussians_ply(tmp_path / "g.ply", GaussianPly(
        means=np.zeros((2, 3)), normals=np.zeros((2, 3)), sh_dc=np.zeros((2, 3)), sh_rest=np.zeros((2, 0, 3)),
        opacity_logit=np.ones(2), log_scales=np.zeros((2, 3)), quats_wxyz=np.tile([1.0, 0, 0, 0], (2, 1))))
    bpy.context.view_layer.objects.active = gaussians_import.import_gaussians(tmp_path / "g.ply")
    _, calls = draw_panel(bpy.types.ESGS_PT_results)
    assert "esgs.compare_to_mesh" in operators(calls)
    assert any(text.endswith(": 2 Gaussians") for text in labels(calls))


def test_the_recorder_catches_what_blender_would_reject():
    class Misspelt:
        bl_idname = "misspelt"

        def draw(self, context):
            self.layout.prop(context.scene.esgs.training, "iteration")

    class UnknownOperator(Misspelt):
        def draw(self, context):
            self.layout.operator("esgs.no_such_thing")

    class BadIcon(Misspelt):
        def draw(self, context):
            self.layout.label(text="hello", icon="NO_SUCH_ICON")

    for cls in (Misspelt, UnknownOperator, BadIcon):
        with pytest.raises((AssertionError, KeyError)):
            draw_panel(cls)


def test_panels_draw_as_an_installed_extension(tmp_path, scene_folder):
    """Blender loads an installed extension as ``bl_ext.<repository>.esgs``: the panels must
    find everything by relative imports (the version label used to fail with
    ``cannot import name '__version__' from 'bl_ext.user_default'``)."""
    profile = tmp_path / "profile"
    repository = profile / "extensions" / "user_default"
    repository.mkdir(parents=True)
    (repository / "esgs").symlink_to(REPO_ROOT, target_is_directory=True)
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(profile)}
    env.pop("ESGS_PYTHON", None)
    done = subprocess.run([sys.executable, panel_drawing.__file__, str(scene_folder)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["addon_id"] == "bl_ext.user_default.esgs"
    assert result["modules"] == []  # nothing of the add-on was imported as plain "esgs"
    for state in ("no_scene", "scene_chosen"):
        drawn = result[state]
        assert drawn["ESGS_PT_main"]["labels"] == [f"ESGS for Blender {result['version']}"]
        assert "esgs.train" in drawn["ESGS_PT_training"]["operators"]
        assert "esgs.render_dataset" in drawn["ESGS_PT_terrain"]["operators"]
        assert "python_path" in drawn["preferences"]["props"]
        assert {"esgs.trainer_setup", "esgs.trainer_check", "esgs.trainer_remove"} <= set(
            drawn["preferences"]["operators"])
        # the set-up's folder is the extension's user directory of this profile
        assert any(text.startswith("Not set up: ") and ".user/user_default/esgs/trainer" in text
                   for text in drawn["preferences"]["labels"])
    assert result["version"] == esgs.__version__
    assert NO_SCENE_HINT in result["no_scene"]["ESGS_PT_training"]["labels"]
    assert NO_SCENE_HINT not in result["scene_chosen"]["ESGS_PT_training"]["labels"]
    assert "prior_source" in result["scene_chosen"]["ESGS_PT_training"]["props"]
    # auto (the default, made before training) first, the scene folder's priors/gt, and computable ones
    assert result["prior_sources"] == ["NONE", "auto", "gt", "ndn", "sfm"]
