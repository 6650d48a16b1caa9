"""Job states saved in a .blend while a job ran (esgs_addon/interrupted_jobs.py): on file load a
job this session does not know becomes 'interrupted' with a message, a known job shows its real
state, and an interrupted training can be resumed from the panel."""
from __future__ import annotations

import json
import sys

import pytest

bpy = pytest.importorskip("bpy")

from esgs.core.apps import jobs  # noqa: E402
from esgs.esgs_addon import interrupted_jobs, training_job  # noqa: E402
from esgs.panels.training_panel import ESGS_PT_training  # noqa: E402
from tests.blender.test_training_operator import draw_panel, fake_trainer, scene_dir  # noqa: E402,F401


def save_and_reopen(path) -> None:
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))


def test_saved_running_jobs_become_interrupted_and_the_training_resumes(tmp_path, fake_trainer, scene_dir):
    training = bpy.context.scene.esgs.training
    training_job.copy_state(training, jobs.JobState(status=jobs.RUNNING, step=40, total=100, loss=0.05, eta_s=75))
    training.last_scene_dir = str(scene_dir)
    training.last_run_dir = str(tmp_path / "run")
    priors = bpy.context.scene.esgs.priors
    priors.status, priors.step, priors.total = jobs.PENDING, 0, 8
    priors.last_scene_dir, priors.last_method = str(scene_dir), "sfm"

    save_and_reopen(tmp_path / "saved.blend")

    training = bpy.context.scene.esgs.training  # the reopened file's settings
    assert training.status == interrupted_jobs.INTERRUPTED
    assert training.error == interrupted_jobs.TRAINING_MESSAGE
    assert "Resume Training" in training.error
    assert (training.step, training.total) == (40, 100)  # how far it got stays visible
    assert training.eta_s == -1.0
    priors = bpy.context.scene.esgs.priors
    assert priors.status == interrupted_jobs.INTERRUPTED
    assert priors.error == interrupted_jobs.PRIORS_MESSAGE

    record = draw_panel(ESGS_PT_training)
    assert ("operator", "esgs.train_resume") in record
    assert ("operator", "esgs.train_cancel") not in record  # nothing to cancel
    assert ("operator", "esgs.compute_priors") in record  # the priors can be started again
    assert ("label", "Last run: interrupted") in record
    assert any(kind == "label" and text.startswith("This training was not running") for kind, text in record)

    # the button does what the message says: the same run folder, --resume
    assert bpy.ops.esgs.train_resume() == {"FINISHED"}
    config = json.loads((tmp_path / "run" / "child_config.json").read_text())
    assert (config["scene"], config["out"]) == (str(scene_dir), str(tmp_path / "run")) and config["resume"] is True
    assert training.status == jobs.FINISHED and training.error == ""


def test_a_training_without_a_run_folder_is_started_again(tmp_path):
    training = bpy.context.scene.esgs.training
    training.status = jobs.RUNNING
    save_and_reopen(tmp_path / "saved.blend")
    training = bpy.context.scene.esgs.training
    assert training.status == interrupted_jobs.INTERRUPTED
    assert training.error == interrupted_jobs.TRAINING_MESSAGE_NO_RUN
    assert ("operator", "esgs.train_resume") not in draw_panel(ESGS_PT_training)


def test_ended_and_empty_states_are_left_alone(tmp_path, scene_dir):
    training = bpy.context.scene.esgs.training
    training_job.copy_state(training, jobs.JobState(status=jobs.FAILED, step=3, total=10, error="out of memory"))
    training.last_scene_dir = str(scene_dir)
    training.last_run_dir = str(tmp_path / "run")
    bpy.context.scene.esgs.priors.status = jobs.FINISHED
    save_and_reopen(tmp_path / "saved.blend")
    assert bpy.context.scene.esgs.training.status == jobs.FAILED
    assert bpy.context.scene.esgs.training.error == "out of memory"
    assert bpy.context.scene.esgs.priors.status == jobs.FINISHED
    assert bpy.context.scene.esgs.priors.error == ""


def test_a_job_of_this_session_shows_its_real_state(tmp_path, scene_dir, monkeypatch):
    # a trainer that only waits: the job is still running when the file is reopened
    monkeypatch.setattr(training_job, "TRAINER_OVERRIDE", [sys.executable, "-c", "import time; time.sleep(60)"])
    job = training_job.start_training(scene_dir, tmp_path / "run", 100)
    try:
        training = bpy.context.scene.esgs.training
        training.last_scene_dir, training.last_run_dir = str(job.scene_dir), str(job.run_dir)
        training_job.copy_state(training, job.state())
        save_and_reopen(tmp_path / "saved.blend")
        assert bpy.context.scene.esgs.training.status == jobs.RUNNING
        assert bpy.context.scene.esgs.training.error == ""
    finally:
        job.cancel(timeout=10.0)
    # the file still says running; the job it names has ended in this session: its state wins
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "saved.blend"))
    assert bpy.context.scene.esgs.training.status == jobs.CANCELLED
