"""The training job runner (core/apps/jobs.py) against small fake trainers with the CLI's interface."""
from __future__ import annotations

import json
import os
import sys
import textwrap
import time
from pathlib import Path

import pytest

from esgs.core.apps import jobs
from esgs.core.errors import ConfigError, DatasetError, ESGSError

# A stand-in for `esgs train` with the same arguments and event protocol. It checkpoints
# its step on SIGTERM and continues from the checkpoint with --resume, like the real one.
FAKE_TRAINER = textwrap.dedent(
    """
    import argparse, json, signal, sys, time
    from pathlib import Path

    parser = argparse.ArgumentParser()
    parser.add_argument("job")
    parser.add_argument("config")
    parser.add_argument("--events", required=True)
    parser.add_argument("--result", required=True)
    parser.add_argument("--stop-file", required=True)
    parser.add_argument("--step-s", type=float, default=0.0)
    parser.add_argument("--crash-at", type=int, default=-1)
    parser.add_argument("--error-event-at", type=int, default=-1)
    args = parser.parse_args()
    config = json.loads(Path(args.config).read_text())
    iterations = config["iterations"]

    out = Path(config["out"])
    out.mkdir(parents=True, exist_ok=True)
    checkpoint = out / "checkpoint.json"
    start = json.loads(checkpoint.read_text())["step"] if config["resume"] and checkpoint.exists() else 0
    (out / f"config_{int(time.time() * 1e6)}.json").write_text(json.dumps(config))
    events = open(args.events, "a", buffering=1)
    step = start

    def emit(kind="progress", message="", **metrics):
        events.write(json.dumps({"step": step, "total": iterations, "stage": "train",
                                 "metrics": metrics, "kind": kind, "message": message,
                                 "time": time.time()}) + "\\n")
        events.flush()

    def stop(*_):
        checkpoint.write_text(json.dumps({"step": step}))
        emit("message", "checkpoint saved")
        sys.exit(0)

    signal.signal(signal.SIGTERM, stop)
    print("fake trainer starting at", start, flush=True)
    while step < iterations:
        if Path(args.stop_file).exists():
            stop()
        step += 1
        if step == args.crash_at:
            print("Traceback (most recent call last):", file=sys.stderr)
            print("RuntimeError: CUDA out of memory (fake)", file=sys.stderr, flush=True)
            sys.exit(3)
        if step == args.error_event_at:
            emit("error", "scene has no cameras (fake)")
            Path(args.result).write_text(json.dumps({"status": "error", "error": {
                "type": "DatasetError", "message": "scene has no cameras (fake)", "path": None, "hint": None}}))
            sys.exit(2)
        emit(loss=1.0 / step, psnr=10.0 + step, n_gaussians=1000 + step, eta_s=(iterations - step) * args.step_s)
        time.sleep(args.step_s)
    (out / "point_cloud.ply").write_text("ply")
    emit("done", "finished", loss=1.0 / step, psnr=10.0 + step, n_gaussians=1000 + step, eta_s=0.0)
    Path(args.result).write_text(json.dumps({"status": "ok", "result": {"step": step}}))
    """
)


@pytest.fixture
def fake_trainer(tmp_path: Path) -> list[str]:
    script = tmp_path / "fake_trainer.py"
    script.write_text(FAKE_TRAINER)
    return [sys.executable, str(script)]


@pytest.fixture
def scene(tmp_path: Path) -> Path:
    folder = tmp_path / "scene"
    folder.mkdir()
    return folder


def test_progress_is_parsed_and_job_finishes(tmp_path, fake_trainer, scene):
    updates = []
    job = jobs.TrainingJob(scene, tmp_path / "run", iterations=20, trainer=fake_trainer)
    job.start()
    state = job.wait(timeout=60, poll_s=0.05, on_update=updates.append)
    assert state.status == jobs.FINISHED, state
    assert state.returncode == 0
    assert (state.step, state.total) == (20, 20)
    assert state.loss == pytest.approx(1.0 / 20)
    assert state.psnr == pytest.approx(30.0)
    assert state.n_gaussians == 1020
    assert state.events_seen == 21  # 20 steps + done
    assert state.fraction == 1.0
    assert (tmp_path / "run" / "point_cloud.ply").exists()
    assert updates and updates[-1].status == jobs.FINISHED
    # the child's own printing is kept for error messages and consoles
    assert any("fake trainer starting at 0" in line for line in job.output_tail)


def test_child_is_started_with_a_config_file_not_flags(tmp_path, scene):
    job = jobs.TrainingJob(scene, tmp_path / "run", iterations=7, config={"width": 480, "seed": 3},
                           trainer=["PY", "-m", "esgs.core.runtime.child"])
    folder = tmp_path / "run" / jobs.JOB_FOLDER
    assert job.command() == ["PY", "-m", "esgs.core.runtime.child", "train", str(folder / "job_config.json"),
                             "--events", str(tmp_path / "run" / "events.jsonl"),
                             "--result", str(folder / "job_result.json"), "--stop-file", str(folder / "job_stop")]
    data = job.config_for_child()
    assert (data["width"], data["seed"], data["iterations"], data["resume"]) == (480, 3, 7, False)
    assert (data["scene"], data["out"]) == (str(scene), str(tmp_path / "run"))
    assert data["stop_file"] == str(folder / "job_stop")
    assert job.config_for_child(resume=True)["resume"] is True


def test_cancel_checkpoints_and_resume_continues(tmp_path, fake_trainer, scene):
    run = tmp_path / "run"
    job = jobs.TrainingJob(scene, run, iterations=400, trainer=fake_trainer + ["--step-s", "0.02"])
    job.start()
    deadline = time.monotonic() + 30
    while job.state().step < 5 and time.monotonic() < deadline:
        time.sleep(0.02)
    state = job.cancel(timeout=30)
    assert state.status == jobs.CANCELLED
    assert not job.running
    stopped_at = json.loads((run / "checkpoint.json").read_text())["step"]
    assert 5 <= stopped_at < 400
    assert not (run / "point_cloud.ply").exists()

    # resume with fewer remaining steps so the test stays short: same job, --resume appended
    job.iterations = stopped_at + 10
    job.trainer = fake_trainer
    job.resume()
    state = job.wait(timeout=60, poll_s=0.05)
    assert state.status == jobs.FINISHED, state
    assert state.step == stopped_at + 10
    # only the resumed run's events count: it restarted from the checkpoint, not from 0
    assert state.events_seen == 11
    config_files = sorted(run.glob("config_*.json"))
    assert len(config_files) == 2
    assert json.loads(config_files[0].read_text())["resume"] is False
    assert json.loads(config_files[1].read_text())["resume"] is True


def test_crash_reports_the_childs_message(tmp_path, fake_trainer, scene):
    job = jobs.TrainingJob(scene, tmp_path / "run", iterations=10, trainer=fake_trainer + ["--crash-at", "4"])
    state = job.start().wait(timeout=60, poll_s=0.05)
    assert state.status == jobs.FAILED
    assert state.returncode == 3
    assert state.error == "RuntimeError: CUDA out of memory (fake)"
    assert state.step == 3


def test_error_event_message_wins(tmp_path, fake_trainer, scene):
    job = jobs.TrainingJob(scene, tmp_path / "run", iterations=10, trainer=fake_trainer + ["--error-event-at", "2"])
    state = job.start().wait(timeout=60, poll_s=0.05)
    assert state.status == jobs.FAILED
    assert state.error == "scene has no cameras (fake)"
    assert type(job.error) is DatasetError  # the child's error comes back as its own type


def test_missing_interpreter_fails_cleanly(tmp_path, scene):
    job = jobs.TrainingJob(scene, tmp_path / "run", iterations=3, trainer=[str(tmp_path / "no_such_python")])
    with pytest.raises(ESGSError, match="could not start the trainer"):
        job.start()
    assert job.state().status == jobs.FAILED
    assert not job.running


def test_bad_arguments_are_config_errors(tmp_path, scene):
    with pytest.raises(ConfigError):
        jobs.TrainingJob(scene, tmp_path / "run", iterations=0)
    job = jobs.TrainingJob(tmp_path / "absent", tmp_path / "run", iterations=3, trainer=["x"])
    with pytest.raises(ConfigError, match="scene folder"):
        job.start()
    with pytest.raises(ConfigError, match="does not exist"):
        jobs.find_python(tmp_path / "missing" / "python")


def test_one_running_job_per_key(tmp_path, fake_trainer, scene):
    first = jobs.TrainingJob(scene, tmp_path / "run1", iterations=400, trainer=fake_trainer + ["--step-s", "0.02"])
    second = jobs.TrainingJob(scene, tmp_path / "run2", iterations=3, trainer=fake_trainer)
    try:
        jobs.start_job("scene-a", first)
        with pytest.raises(ESGSError, match="already running"):
            jobs.start_job("scene-a", second)
        assert jobs.get_job("scene-a") is first
    finally:
        first.cancel(timeout=30)
    jobs.start_job("scene-a", second)
    assert second.wait(timeout=60, poll_s=0.05).status == jobs.FINISHED
    jobs.forget_job("scene-a")
    assert jobs.get_job("scene-a") is None


def test_stop_all_jobs_leaves_no_child(tmp_path, fake_trainer, scene):
    job = jobs.TrainingJob(scene, tmp_path / "run", iterations=400, trainer=fake_trainer + ["--step-s", "0.02"])
    job.start()
    while job.state().step < 2:
        time.sleep(0.02)
    jobs.stop_all_jobs(timeout=30)
    assert job._process.poll() is not None
    assert job.wait(timeout=10).status == jobs.CANCELLED


def test_find_python_prefers_explicit_then_environment(tmp_path, monkeypatch):
    python = tmp_path / "python"
    python.write_text("")
    assert jobs.find_python(python) == str(python)
    monkeypatch.setenv("ESGS_PYTHON", str(python))
    assert jobs.find_python() == str(python)
    monkeypatch.delenv("ESGS_PYTHON")
    assert Path(jobs.find_python()).is_file()


def test_partial_lines_are_not_parsed_early(tmp_path):
    job = jobs.TrainingJob(tmp_path, tmp_path / "run", iterations=5, trainer=["x"])
    job.events_path.parent.mkdir(parents=True)
    line = json.dumps({"step": 2, "total": 5, "metrics": {"loss": 0.5}, "kind": "progress"})
    job.events_path.write_text(line[:10])
    offset, pending = job._read_events(0, b"")
    assert job.state().events_seen == 0 and pending == line[:10].encode()
    job.events_path.write_text(line + "\n" + "not json\n")
    offset, pending = job._read_events(offset, pending)
    state = job.state()
    assert (state.events_seen, state.step, state.loss) == (1, 2, 0.5)
    assert pending == b""


def test_summary_and_duration():
    state = jobs.JobState(status=jobs.RUNNING, step=3, total=10, loss=0.25, psnr=21.456, n_gaussians=12345, eta_s=3725)
    assert state.summary() == "running  step 3/10  loss 0.25  training PSNR 21.46 dB  12,345 Gaussians  ETA 1:02:05"
    assert jobs.format_duration(65) == "1:05"


def test_the_psnr_of_the_final_event_is_labelled_held_out(tmp_path):
    job = jobs.TrainingJob(tmp_path, tmp_path / "run", iterations=10, trainer=["x"])
    job.events_path.parent.mkdir(parents=True)
    train = {"step": 5, "total": 10, "stage": "train", "kind": "progress", "metrics": {"psnr": 25.0}}
    done = {"step": 10, "total": 10, "stage": "train", "kind": "done", "metrics": {"psnr": 21.0}}
    job.events_path.write_text(json.dumps(train) + "\n")
    offset, pending = job._read_events(0, b"")
    assert not job.state().psnr_held_out and "training PSNR 25.00" in job.state().summary()
    with job.events_path.open("a") as handle:
        handle.write(json.dumps(done) + "\n")
    job._read_events(offset, pending)
    assert job.state().psnr_held_out and "held-out PSNR 21.00" in job.state().summary()


def test_cancel_without_waiting_returns_at_once(tmp_path, fake_trainer, scene):
    job = jobs.TrainingJob(scene, tmp_path / "run", iterations=400, trainer=fake_trainer + ["--step-s", "0.02"])
    job.start()
    while job.state().step < 2:
        time.sleep(0.02)
    job.cancel(timeout=30, wait=False)
    assert job.wait(timeout=30, poll_s=0.05).status == jobs.CANCELLED
    assert (tmp_path / "run" / "checkpoint.json").exists()


def test_sigterm_while_waiting_stops_the_child_too(tmp_path, fake_trainer, scene):
    """A killed headless script must not leave an orphan trainer behind."""
    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        from esgs.core.apps import jobs
        job = jobs.TrainingJob({str(scene)!r}, {str(tmp_path / 'run')!r}, iterations=100000,
                               trainer={fake_trainer + ['--step-s', '0.01']!r})
        job.start()
        print(job._process.pid, flush=True)
        job.wait(poll_s=0.05)
    """))
    import signal
    import subprocess

    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    child_pid = int(parent.stdout.readline())
    time.sleep(0.5)
    parent.send_signal(signal.SIGTERM)
    assert parent.wait(timeout=60) == 143
    assert (tmp_path / "run" / "checkpoint.json").exists()  # the child checkpointed on its SIGTERM
    with pytest.raises(ProcessLookupError):
        os.kill(child_pid, 0)


def test_missing_module_failure_names_the_interpreter(tmp_path, scene):
    script = tmp_path / "needs_torch.py"
    script.write_text("import no_such_module_for_esgs_tests\n")
    job = jobs.TrainingJob(scene, tmp_path / "run", iterations=3, trainer=[sys.executable, str(script)])
    state = job.start().wait(timeout=60, poll_s=0.05)
    assert state.status == jobs.FAILED
    assert state.error.startswith("ModuleNotFoundError: No module named 'no_such_module_for_esgs_tests'")
    assert sys.executable in state.error and "preferences" in state.error


def test_installed_trainer_has_the_interface_the_runner_uses():
    if not jobs.trainer_available():
        pytest.skip("the engine's trainer (esgs.core.train) is not installed")
    from esgs.core.runtime.entry_points import entry_point, load_job_function

    assert callable(load_job_function("train"))
    assert entry_point("train").watches_stop_file  # the trainer checkpoints on the stop file itself
    command = jobs.child_command("PY")
    assert command == ["PY", "-m", "esgs.core.runtime.child"]
