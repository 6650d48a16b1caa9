"""A trainer process killed with SIGKILL resumes and finishes; SIGTERM checkpoints and exits."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from esgs.core.train.checkpoint import list_checkpoints

ITERATIONS = 80

# each test starts two trainer processes (torch import + a short run): ~30 s on a loaded 2-core machine
pytestmark = pytest.mark.slow


def _command(scene: Path, run: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "esgs.core", "train", str(scene), "--out", str(run), "--iterations", str(ITERATIONS),
            "--backend", "reference", "--threads", "1", "--checkpoint-every", "4", "--progress-every", "4",
            "--max-gaussians", "300", "--no-lpips", "--no-save-renders", "--quiet", *extra]


def _start_and_wait_for_checkpoint(scene: Path, run: Path) -> subprocess.Popen:
    process = subprocess.Popen(_command(scene, run), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not list_checkpoints(run / "checkpoints"):
        if process.poll() is not None:
            pytest.fail(f"the trainer ended early: {process.communicate()}")
        if time.monotonic() > deadline:
            process.kill()
            pytest.fail("no checkpoint within 120 s")
        time.sleep(0.02)
    assert process.poll() is None, "the trainer finished before it could be interrupted"
    return process


def _finished_run(run: Path) -> dict:
    from esgs.core.formats.ply import read_gaussians_ply

    result = json.loads((run / "train_result.json").read_text())
    assert result["status"] == "completed" and result["step"] == ITERATIONS
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["psnr"] > 10 and len(metrics["views"]) == 2
    assert len(read_gaussians_ply(run / "point_cloud.ply")) == result["n_gaussians"]
    return result


def test_sigkill_mid_training_then_resume_finishes(tiny_scene, tmp_path):
    run = tmp_path / "run"
    process = _start_and_wait_for_checkpoint(tiny_scene, run)
    os.kill(process.pid, signal.SIGKILL)
    process.communicate(timeout=60)
    assert process.returncode == -signal.SIGKILL
    assert not (run / "train_result.json").exists()
    killed_at = list_checkpoints(run / "checkpoints")[-1][0]
    assert killed_at < ITERATIONS
    resumed = subprocess.run(_command(tiny_scene, run, "--resume"), capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    _finished_run(run)
    events = [json.loads(line) for line in (run / "events.jsonl").read_text().splitlines()]
    assert any(e["kind"] == "message" and f"resuming from step {killed_at}" in e["message"] for e in events) or \
        any(e["kind"] == "message" and "resuming from step" in e["message"] for e in events)
    assert not list((run / "checkpoints").glob(".*"))


def test_sigterm_saves_a_checkpoint_and_exits_cleanly(tiny_scene, tmp_path):
    run = tmp_path / "run"
    process = _start_and_wait_for_checkpoint(tiny_scene, run)
    process.send_signal(signal.SIGTERM)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 143, stderr
    assert "Traceback" not in stderr and "--resume" in stdout
    result = json.loads((run / "train_result.json").read_text())
    assert result["status"] == "interrupted" and result["step"] < ITERATIONS
    assert list_checkpoints(run / "checkpoints")[-1][0] == result["step"]  # saved where it stopped
    assert not (run / "metrics.json").exists()
    resumed = subprocess.run(_command(tiny_scene, run, "--resume"), capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    _finished_run(run)
