"""The interactive path of training (operators/train.py, esgs_addon/training_job.py) and of
priors (operators/priors.py): what a
Blender with a window does, driven by hand.

With a window the Train and Resume operators return at once and a timer follows the job:
progress into ``scene.esgs.training`` and the panel, Cancel (the trainer saves a
checkpoint), Resume, the result imported when the job finishes. Timers never fire under
the bpy module, so these tests catch the function the operator registers and call it
themselves, and show the operators a ``bpy.app.background`` of False (the real attribute
is read-only).

The fake trainer here behaves like the real one where the add-on can tell: it trains step
by step (a sleep each), stops on the stop file, on ``RUN/STOP`` or on SIGTERM by saving a
checkpoint in ``RUN/checkpoints`` and writing its PLY and an ``interrupted`` result, resumes
from its newest checkpoint, and can crash part-way (exit status 1, a message on stderr).
"""
from __future__ import annotations

import json
import sys
import textwrap
import time
from pathlib import Path

import pytest

bpy = pytest.importorskip("bpy")

from esgs.core.apps import jobs  # noqa: E402
from esgs.esgs_addon import gaussians_import, priors_job, training_job  # noqa: E402
from esgs.operators import priors as priors_operators  # noqa: E402
from esgs.operators import train as train_operators  # noqa: E402
from tests.blender.panel_drawing import draw_panel  # noqa: E402

N_GAUSSIANS = 25

STEPPING_TRAINER = textwrap.dedent(
    """
    import argparse, json, os, signal, sys, time
    from pathlib import Path
    import numpy as np
    from esgs.core.formats.ply import GaussianPly, write_gaussians_ply

    parser = argparse.ArgumentParser()
    parser.add_argument("job")
    parser.add_argument("config")
    parser.add_argument("--events", required=True)
    parser.add_argument("--result", required=True)
    parser.add_argument("--stop-file", required=True)
    parser.add_argument("--step-s", type=float, default=0.05)
    parser.add_argument("--crash-at", type=int, default=0)
    parser.add_argument("--damaged-ply", action="store_true")
    args = parser.parse_args()
    config = json.loads(Path(args.config).read_text())
    iterations, out = config["iterations"], Path(config["out"])
    checkpoints = out / "checkpoints"
    stop_files = [out / "STOP", Path(config.get("stop_file") or args.stop_file)]
    signals = []
    signal.signal(signal.SIGTERM, lambda number, frame: signals.append("SIGTERM"))

    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(config))  # the real trainer saves its settings first
    for path in stop_files:
        path.unlink(missing_ok=True)  # a request left by an earlier session must not stop this one
    start = 0
    if config.get("resume"):
        found = sorted(checkpoints.glob("step_*.pt"))
        if found:
            start = json.loads(found[-1].read_text())["step"]
    with open(out / "sessions.jsonl", "a") as sessions:
        sessions.write(json.dumps({"resume": bool(config.get("resume")), "first_step": start + 1,
                                   "pid": os.getpid()}) + "\\n")

    def event(**data):
        with open(args.events, "a") as events:
            events.write(json.dumps(data) + "\\n")

    def save_checkpoint(step):
        checkpoints.mkdir(exist_ok=True)
        (checkpoints / f"step_{step:09d}.pt").write_text(json.dumps({"step": step}))

    status, step = "completed", start
    for step in range(start + 1, iterations + 1):
        time.sleep(args.step_s)  # the training step
        if step == args.crash_at:
            sys.exit("RuntimeError: the fake trainer ran out of memory")
        if signals or any(path.exists() for path in stop_files):
            reason = signals[0] if signals else "stop request"
            for path in stop_files:
                path.unlink(missing_ok=True)
            save_checkpoint(step)
            status = "interrupted"
            print(f"{reason} received: checkpoint saved at step {step}; resume with --resume", flush=True)
            break
        event(step=step, total=iterations, stage="train", kind="progress",
              metrics={"loss": 1.0 / step, "psnr": 20.0 + 0.1 * step, "n_gaussians": %(n)d,
                       "eta_s": args.step_s * (iterations - step)})
    if status == "completed":
        save_checkpoint(step)
    # like the real trainer, a stopped run writes its PLY too: only its status tells it apart
    side = int(round(%(n)d ** 0.5))
    u = np.linspace(-0.75, 0.75, side)
    x, y = np.meshgrid(u, u)
    means = np.column_stack([x.ravel(), y.ravel(), np.full(%(n)d, 0.01)])
    write_gaussians_ply(out / "point_cloud.ply", GaussianPly(
        means=means, normals=np.zeros((%(n)d, 3)), sh_dc=np.zeros((%(n)d, 3)), sh_rest=np.zeros((%(n)d, 0, 3)),
        opacity_logit=np.full(%(n)d, 3.0), log_scales=np.full((%(n)d, 3), -3.0),
        quats_wxyz=np.tile([1.0, 0, 0, 0], (%(n)d, 1))))
    if args.damaged_ply:  # cut short, as by a full disk
        data = (out / "point_cloud.ply").read_bytes()
        (out / "point_cloud.ply").write_bytes(data[:len(data) // 2])
    result = {"run_dir": str(out), "status": status, "step": step, "iterations": iterations,
              "n_gaussians": %(n)d}
    (out / "train_result.json").write_text(json.dumps(result))
    event(step=step, total=iterations, stage="train", kind="done", metrics={"n_gaussians": %(n)d}, message=status)
    Path(args.result).write_text(json.dumps({"status": "ok", "result": result}))
    """
) % {"n": N_GAUSSIANS}


@pytest.fixture
def trainer(tmp_path, monkeypatch):
    """Use the stepping fake trainer; ``trainer(*flags)`` changes its flags."""
    script = tmp_path / "stepping_trainer.py"
    script.write_text(STEPPING_TRAINER)

    def use(*flags: str) -> None:
        monkeypatch.setattr(training_job, "TRAINER_OVERRIDE", [sys.executable, str(script), *flags])

    use()
    return use


@pytest.fixture
def scene_dir(tmp_path) -> Path:
    from tests.blender.colmap_helpers import synthetic_model, write_scene

    return write_scene(tmp_path, synthetic_model(), name="scene")


class _Delegate:
    """``target`` with some attributes replaced."""

    def __init__(self, target, **overrides):
        self.__dict__["_target"] = target
        self.__dict__.update(overrides)

    def __getattr__(self, name):
        return getattr(self._target, name)


@pytest.fixture
def timers(monkeypatch):
    """Blender with a window, as the training operators see it; returns the list of the
    functions registered as timers (in order), which the test calls itself."""
    windowed = _Delegate(bpy, app=_Delegate(bpy.app, background=False))
    monkeypatch.setattr(train_operators, "bpy", windowed)
    monkeypatch.setattr(priors_operators, "bpy", windowed)
    registered = []

    def register(function, first_interval=0.0, persistent=False):
        assert persistent  # a training outlives loading another file
        registered.append(function)

    monkeypatch.setattr(bpy.app.timers, "register", register)
    yield registered
    jobs.stop_all_jobs(timeout=5.0)  # a failing test must not leave a trainer running


def drive(poll, until=lambda: False, timeout_s: float = 20.0):
    """Call the timer function ``poll`` as Blender would (every few hundredths of a second
    here) until ``until()`` holds (returns the last return value) or it unregisters itself
    (returns None)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        interval = poll()
        if interval is None:
            return None
        assert interval == training_job.POLL_INTERVAL_S  # still registered: called again
        if until():
            return interval
        time.sleep(0.03)
    pytest.fail("the timer never saw what the test waited for")


def imported_objects(run_dir: Path) -> list:
    return [obj for obj in bpy.data.objects if obj.get(training_job.PROP_RUN_DIR) == str(run_dir)]


def labels(calls) -> list[str]:
    return [call.text for call in calls if call.name == "label"]


def operators(calls) -> list[str]:
    return [call.text for call in calls if call.name == "operator"]


def setup_training(tmp_path: Path, scene_dir: Path, iterations: int):
    settings = bpy.context.scene.esgs.training
    settings.scene_dir = str(scene_dir)
    settings.run_dir = str(tmp_path / "run")
    settings.iterations = iterations
    settings.import_result = True
    return settings, tmp_path / "run"


def test_progress_cancel_with_checkpoint_resume_and_import_at_the_end(tmp_path, trainer, scene_dir, timers):
    settings, run_dir = setup_training(tmp_path, scene_dir, iterations=300)
    objects_before = len(bpy.data.objects)

    started = time.monotonic()
    assert bpy.ops.esgs.train() == {"FINISHED"}
    assert time.monotonic() - started < 5.0  # returned at once: the timer follows the job
    assert len(timers) == 1 and settings.status == "running"
    job = jobs.get_job(training_job.job_key(scene_dir))
    assert job.running and settings.last_run_dir == str(run_dir)

    # progress: the timer copies the job's state into the settings, the panel shows it
    poll = timers[0]
    drive(poll, until=lambda: settings.step >= 3 and settings.psnr >= 0)
    assert settings.status == "running" and settings.total == 300
    assert 0.0 < settings.progress < 1.0 and settings.n_gaussians == N_GAUSSIANS
    _, calls = draw_panel(bpy.types.ESGS_PT_training)
    bars = [call for call in calls if call.name == "progress"]
    assert len(bars) == 1 and bars[0].kwargs["text"] == f"{settings.step:,} / 300"
    assert f"Training PSNR (last views) {settings.psnr:.2f} dB" in labels(calls)
    assert "esgs.train_cancel" in operators(calls) and "esgs.train" not in operators(calls)

    # Cancel: returns at once; the trainer saves a checkpoint and stops; nothing is imported
    started = time.monotonic()
    assert bpy.ops.esgs.train_cancel() == {"FINISHED"}
    assert time.monotonic() - started < 2.0
    assert drive(poll) is None  # the timer unregisters itself once the job has ended
    assert not job.running and job.state().returncode == 0
    assert settings.status == "cancelled" and settings.error == ""
    checkpoints = sorted((run_dir / "checkpoints").glob("step_*.pt"))
    assert len(checkpoints) == 1
    stopped_at = json.loads(checkpoints[0].read_text())["step"]
    assert 3 <= stopped_at < 300
    assert (run_dir / "point_cloud.ply").is_file()  # written, as the real trainer does, but not imported
    assert imported_objects(run_dir) == [] and len(bpy.data.objects) == objects_before
    _, calls = draw_panel(bpy.types.ESGS_PT_training)
    assert "Last run: cancelled" in labels(calls)
    assert {"esgs.train", "esgs.train_resume"} <= set(operators(calls))
    assert not [call for call in calls if call.name == "progress"]
    assert bpy.ops.esgs.train_cancel() == {"CANCELLED"}  # nothing runs anymore

    # Resume: continues from the checkpoint to the end, and the timer imports the result
    settings.iterations = stopped_at + 20
    assert bpy.ops.esgs.train_resume() == {"FINISHED"}
    assert len(timers) == 2 and settings.status == "running"
    resumed = jobs.get_job(training_job.job_key(scene_dir))
    assert resumed is not job and resumed.run_dir == run_dir
    poll = timers[1]
    drive(poll, until=lambda: settings.step > 0)
    assert settings.step > stopped_at  # the resumed run's steps continue the stopped one's
    assert drive(poll) is None
    assert settings.status == "finished" and settings.error == ""
    assert (settings.step, settings.total, settings.progress) == (stopped_at + 20, stopped_at + 20, 1.0)
    sessions = [json.loads(line) for line in (run_dir / "sessions.jsonl").read_text().splitlines()]
    assert [(s["resume"], s["first_step"]) for s in sessions] == [(False, 1), (True, stopped_at + 1)]
    assert json.loads((run_dir / ".job" / "job_config.json").read_text())["resume"] is True

    (obj,) = imported_objects(run_dir)
    assert gaussians_import.is_gaussian_object(obj) and len(obj.data.points) == N_GAUSSIANS
    assert obj.name in bpy.context.scene.objects
    _, calls = draw_panel(bpy.types.ESGS_PT_training)
    assert "Last run: finished" in labels(calls) and "esgs.train_resume" not in operators(calls)


def test_a_failing_trainer_leaves_an_error_and_imports_nothing(tmp_path, trainer, scene_dir, timers):
    trainer("--crash-at", "8")
    settings, run_dir = setup_training(tmp_path, scene_dir, iterations=50)
    objects_before = len(bpy.data.objects)
    assert bpy.ops.esgs.train() == {"FINISHED"}
    assert drive(timers[0]) is None
    assert settings.status == "failed"
    assert settings.error == "RuntimeError: the fake trainer ran out of memory"
    assert 0 < settings.step < 8 and settings.progress < 1.0
    assert len(bpy.data.objects) == objects_before and imported_objects(run_dir) == []
    _, calls = draw_panel(bpy.types.ESGS_PT_training)
    assert "Last run: failed" in labels(calls)
    assert "RuntimeError: the fake trainer ran out of memory" in " ".join(labels(calls))
    assert {"esgs.train", "esgs.train_resume"} <= set(operators(calls))


def test_a_result_that_cannot_be_imported_is_an_error_not_a_half_object(tmp_path, trainer, scene_dir, timers):
    trainer("--damaged-ply")
    settings, run_dir = setup_training(tmp_path, scene_dir, iterations=5)
    objects_before, clouds_before = len(bpy.data.objects), len(bpy.data.pointclouds)
    assert bpy.ops.esgs.train() == {"FINISHED"}
    assert drive(timers[0]) is None
    assert settings.status == "finished"
    assert settings.error.startswith("training finished but importing failed:")
    assert (len(bpy.data.objects), len(bpy.data.pointclouds)) == (objects_before, clouds_before)
    _, calls = draw_panel(bpy.types.ESGS_PT_training)
    assert any(text.startswith("training finished but importing failed") for text in labels(calls))


def test_a_timer_follows_only_the_job_it_was_started_for(tmp_path, trainer, scene_dir, timers):
    """Resume pressed before the old timer saw its job end (the next poll is half a second
    away) must not leave two timers following, and importing, the new job."""
    settings, run_dir = setup_training(tmp_path, scene_dir, iterations=300)
    assert bpy.ops.esgs.train() == {"FINISHED"}
    first = timers[0]
    drive(first, until=lambda: settings.step >= 2)
    job = jobs.get_job(training_job.job_key(scene_dir))
    assert bpy.ops.esgs.train_cancel() == {"FINISHED"}
    job.wait(timeout=15.0)
    assert job.state().status == "cancelled"

    settings.iterations = 30
    assert bpy.ops.esgs.train_resume() == {"FINISHED"}  # before the first timer's next call
    assert first() is None  # its job has ended: it stops, whatever runs now for the scene
    assert settings.status == "running"  # and leaves the new job's state alone
    assert drive(timers[1]) is None
    assert settings.status == "finished"
    assert len(imported_objects(run_dir)) == 1


def test_headless_cancel_waits_for_the_checkpoint(tmp_path, trainer, scene_dir):
    """Headless (no window, no timer) Cancel blocks until the trainer has stopped."""
    assert bpy.app.background
    settings, run_dir = setup_training(tmp_path, scene_dir, iterations=300)
    job = training_job.start_training(scene_dir, run_dir, 300)  # a script starts it, non-blocking
    settings.last_scene_dir, settings.last_run_dir = str(scene_dir), str(run_dir)
    deadline = time.monotonic() + 15.0
    while job.state().step < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert bpy.ops.esgs.train_cancel() == {"FINISHED"}
    assert not job.running and settings.status == "cancelled"
    assert len(list((run_dir / "checkpoints").glob("step_*.pt"))) == 1
    assert bpy.ops.esgs.train_cancel() == {"CANCELLED"}


def test_a_trainer_stopped_by_sigterm_counts_as_cancelled(tmp_path, trainer, scene_dir, timers):
    """Stopped from outside (SIGTERM: the system shutting down, a user's kill): the trainer
    checkpoints like on Cancel, and the timer shows a cancelled run it does not import."""
    settings, run_dir = setup_training(tmp_path, scene_dir, iterations=300)
    assert bpy.ops.esgs.train() == {"FINISHED"}
    drive(timers[0], until=lambda: settings.step >= 2)
    jobs.get_job(training_job.job_key(scene_dir))._process.terminate()
    assert drive(timers[0]) is None
    assert settings.status == "cancelled"
    assert len(list((run_dir / "checkpoints").glob("step_*.pt"))) == 1
    assert imported_objects(run_dir) == []


STEPPING_PRIORS = textwrap.dedent(
    """
    import argparse, json, sys, time
    from pathlib import Path

    parser = argparse.ArgumentParser()
    parser.add_argument("job")
    parser.add_argument("config")
    parser.add_argument("--events", required=True)
    parser.add_argument("--result", required=True)
    parser.add_argument("--stop-file", required=True)
    args = parser.parse_args()
    for view in range(1, 201):
        time.sleep(0.05)
        if Path(args.stop_file).exists():  # as the runtime's stop watcher ends a job
            with open(args.events, "a") as events:
                events.write(json.dumps({"step": 0, "total": 0, "stage": "priors", "kind": "message",
                                         "message": "stopped on request"}) + "\\n")
            Path(args.result).write_text(json.dumps({"status": "cancelled"}))
            sys.exit(130)
        with open(args.events, "a") as events:
            events.write(json.dumps({"step": view, "total": 200, "stage": "sfm", "kind": "progress"}) + "\\n")
    sys.exit("the fake priors job was never cancelled")
    """
)


def test_priors_progress_and_cancel_through_the_timer(tmp_path, scene_dir, timers, monkeypatch):
    script = tmp_path / "stepping_priors.py"
    script.write_text(STEPPING_PRIORS)
    monkeypatch.setattr(priors_job, "COMMAND_OVERRIDE", [sys.executable, str(script)])
    bpy.context.scene.esgs.training.scene_dir = str(scene_dir)
    settings = bpy.context.scene.esgs.priors
    settings.method = "sfm"

    started = time.monotonic()
    assert bpy.ops.esgs.compute_priors() == {"FINISHED"}
    assert time.monotonic() - started < 5.0 and len(timers) == 1
    job = priors_job.running_job(scene_dir)
    assert job is not None and settings.status == "running"
    assert not bpy.ops.esgs.compute_priors.poll()  # one job per scene folder
    drive(timers[0], until=lambda: settings.step >= 2)
    assert settings.total == 200 and 0.0 < settings.progress < 1.0
    _, calls = draw_panel(bpy.types.ESGS_PT_training)
    assert "esgs.compute_priors_cancel" in operators(calls)
    assert any(call.name == "progress" for call in calls)

    started = time.monotonic()
    assert bpy.ops.esgs.compute_priors_cancel() == {"FINISHED"}
    assert time.monotonic() - started < 2.0  # the timer sees the end
    assert drive(timers[0]) is None
    assert settings.status == "cancelled" and job.state().returncode == 130
    assert not job.events_dir.exists()  # cleaned up at the end
    assert not (scene_dir / "priors" / "sfm").exists()
    assert bpy.ops.esgs.compute_priors.poll()
    assert bpy.ops.esgs.compute_priors_cancel() == {"CANCELLED"}


def test_the_timer_follows_its_scene_through_a_rename_and_no_other_of_that_name(tmp_path, trainer, scene_dir,
                                                                                timers):
    settings, run_dir = setup_training(tmp_path, scene_dir, iterations=30)
    started_from = bpy.context.scene
    name = started_from.name
    assert bpy.ops.esgs.train() == {"FINISHED"}
    drive(timers[0], until=lambda: settings.step >= 2)
    started_from.name = "Renamed while training"
    other = bpy.data.scenes.new(name)  # now the scene of the name the timer was given
    assert drive(timers[0]) is None
    assert started_from.esgs.training.status == "finished"
    (obj,) = imported_objects(run_dir)
    assert obj.name in started_from.objects and obj.name not in other.objects
    assert other.esgs.training.status == "" and other.esgs.training.step == 0


def test_a_file_loaded_while_training_gets_neither_its_state_nor_its_result(tmp_path, trainer, scene_dir, timers):
    settings, run_dir = setup_training(tmp_path, scene_dir, iterations=30)
    name = bpy.context.scene.name
    assert bpy.ops.esgs.train() == {"FINISHED"}
    drive(timers[0], until=lambda: settings.step >= 2)
    job = jobs.get_job(training_job.job_key(scene_dir))
    bpy.ops.wm.read_homefile(use_empty=True)  # another file; its scene has the same name
    assert bpy.context.scene.name == name
    assert drive(timers[0]) is None
    assert job.state().status == "finished"
    assert bpy.context.scene.esgs.training.status == "" and bpy.context.scene.esgs.training.step == 0
    assert imported_objects(run_dir) == [] and len(bpy.data.objects) == 0


def test_the_same_file_reopened_while_training_is_followed_to_the_import(tmp_path, trainer, scene_dir, timers):
    settings, run_dir = setup_training(tmp_path, scene_dir, iterations=40)
    assert bpy.ops.esgs.train() == {"FINISHED"}
    drive(timers[0], until=lambda: settings.step >= 2)
    blend = tmp_path / "saved_while_training.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    reopened = bpy.context.scene.esgs.training
    assert reopened.last_run_dir == str(run_dir)
    assert drive(timers[0]) is None
    assert reopened.status == "finished" and reopened.step == 40
    (obj,) = imported_objects(run_dir)
    assert obj.name in bpy.context.scene.objects
