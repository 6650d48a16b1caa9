"""The training-time estimate the Blender panel shows (esgs.core.apps.estimate): the default
figures, the measured basis preferred when a finished run is there, linear pixel scaling,
and the auto priors' one-time term."""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from esgs.core.apps import estimate
from esgs.core.apps.estimate import BASIS_MEASURED, BASIS_TYPICAL, estimate_training_seconds


def write_scene(folder: Path, views: int = 8, width: int = 640, height: int = 360) -> Path:
    """A scene folder whose COLMAP model (text) has ``views`` images of one camera."""
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    (folder / "images").mkdir()
    (model / "cameras.txt").write_text(f"1 PINHOLE {width} {height} 500 500 {width / 2} {height / 2}\n")
    (model / "images.txt").write_text("".join(f"{i} 1 0 0 0 0 0 {i} 1 view_{i:03d}.png\n\n" for i in range(1, views + 1)))
    (model / "points3D.txt").write_text("")
    return folder


def write_run(folder: Path, *, step_s: float = 0.1, steps: int = 100, views: int = 8, size=(160, 90),
              method: str = "3dgs", threads: int = 2, backend: str = "auto", n_gaussians: int = 20_000,
              status: str = "completed", scene: str = "", mtime: float | None = None) -> Path:
    """A finished run folder: progress events every 10 steps at ``step_s`` a step (after a slow
    first interval, and with a pause before the last event, neither of which counts)."""
    folder.mkdir(parents=True)
    events = [{"step": 0, "stage": "train", "kind": "message", "time": 0.0}]
    when = 100.0
    events.append({"step": 10, "stage": "train", "kind": "progress", "time": when, "metrics": {}})
    for step in range(20, steps + 11, 10):
        when += 10 * step_s
        events.append({"step": step, "stage": "train", "kind": "progress", "time": when, "metrics": {}})
    events.append({"step": steps + 20, "stage": "train", "kind": "progress", "time": when + 5000.0, "metrics": {}})
    events.append({"step": 1, "stage": "eval", "kind": "progress", "time": when + 5001.0, "metrics": {}})
    (folder / "events.jsonl").write_text("".join(json.dumps(event) + "\n" for event in events))
    (folder / "config.json").write_text(json.dumps({"scene": scene, "method": method, "threads": threads,
                                                    "backend": backend, "width": 0, "resolution": 1}))
    (folder / "cameras.json").write_text(json.dumps([{"width": size[0], "height": size[1]}] * views))
    (folder / "train_result.json").write_text(json.dumps({"status": status, "step": steps + 20,
                                                          "n_gaussians": n_gaussians, "elapsed_s": 1.0}))
    if mtime is not None:
        os.utime(folder / "train_result.json", (mtime, mtime))
    return folder


def test_the_default_figures_at_their_own_size():
    # 15 s start + 2000 steps x 0.20 s (ESGS at 320x180 on 2 cores) + 2 held-out views of 12 x 0.5 s
    seconds, basis = estimate_training_seconds(12, 320, 180, 2000, "esgs", threads=2)
    assert seconds == pytest.approx(15 + 400 + 1.0)
    assert basis == BASIS_TYPICAL
    assert estimate_training_seconds(12, 320, 180, 2000, "esgs") == (seconds, basis)  # threads unknown: 2 cores
    # 3DGS: 0.12 s a step; Mip-Splatting and DropoutGS cost as much; an unknown method too
    assert estimate_training_seconds(12, 320, 180, 2000, "3dgs")[0] == pytest.approx(15 + 240 + 1.0)
    for method in ("mip-splatting", "dropout-gs", "some-plugin"):
        assert estimate_training_seconds(12, 320, 180, 2000, method)[0] == pytest.approx(15 + 240 + 1.0)


def test_steps_scale_with_the_pixels():
    small = estimate_training_seconds(8, 320, 180, 1000, "3dgs", test_every=0)[0] - estimate.STARTUP_S
    large = estimate_training_seconds(8, 640, 360, 1000, "3dgs", test_every=0)[0] - estimate.STARTUP_S
    assert small == pytest.approx(120.0) and large == pytest.approx(4 * 120.0)


def test_held_out_views_add_their_evaluation():
    assert estimate.held_out_views(12, 8) == 2 and estimate.held_out_views(8, 8) == 1
    assert estimate.held_out_views(12, 0) == 0
    with_eval = estimate_training_seconds(17, 320, 180, 100, "3dgs", test_every=8)[0]
    without = estimate_training_seconds(17, 320, 180, 100, "3dgs", test_every=0)[0]
    assert with_eval - without == pytest.approx(3 * estimate.EVAL_VIEW_S)


def test_other_thread_counts_say_so():
    assert estimate.thread_factor(2) == pytest.approx(1.0)
    assert estimate.thread_factor(1) == pytest.approx(1.0 / 0.725)
    seconds, basis = estimate_training_seconds(8, 320, 180, 1000, "3dgs", threads=1, test_every=0)
    assert seconds == pytest.approx(15 + 120 / 0.725)
    assert basis == "2-core figures scaled to 1 thread"
    seconds, basis = estimate_training_seconds(8, 320, 180, 1000, "3dgs", threads=16, test_every=0)
    assert seconds == pytest.approx(15 + 120 * (0.45 + 0.55 / 16) / 0.725) and "16 threads" in basis


def test_a_gaussian_cap_below_the_reference_count_shortens_steps():
    capped = estimate_training_seconds(8, 320, 180, 1000, "3dgs", test_every=0, max_gaussians=10_000)[0]
    assert capped == pytest.approx(15 + 120 / 4)
    assert estimate_training_seconds(8, 320, 180, 1000, "3dgs", test_every=0, max_gaussians=3_000_000)[0] \
        == pytest.approx(15 + 120)


def test_a_finished_run_is_read_at_its_steady_rate(tmp_path):
    run = estimate.read_measured_run(write_run(tmp_path / "run", step_s=0.1, steps=100))
    assert run is not None
    # the slow first interval (set-up) and the pause before the last event are left out
    assert run.step_s == pytest.approx(0.1) and run.steps == 100
    assert (run.width, run.height, run.method, run.n_gaussians, run.threads) == (160, 90, "3dgs", 20_000, 2)


def test_runs_that_measure_nothing_are_skipped(tmp_path):
    assert estimate.read_measured_run(write_run(tmp_path / "short", steps=10)) is None
    assert estimate.read_measured_run(write_run(tmp_path / "stopped", status="interrupted")) is None
    assert estimate.read_measured_run(tmp_path / "missing") is None
    broken = write_run(tmp_path / "broken")
    (broken / "train_result.json").write_text("{")
    assert estimate.read_measured_run(broken) is None


def test_the_measured_basis_is_preferred_and_scaled(tmp_path):
    run = estimate.read_measured_run(write_run(tmp_path / "run", step_s=0.1, size=(160, 90), method="3dgs"))
    # 4x the pixels, ESGS for 3DGS (0.20 / 0.12), same threads: 0.1 x 4 x 5/3 s a step
    seconds, basis = estimate_training_seconds(8, 320, 180, 1000, "esgs", threads=2, measured=run)
    assert basis == BASIS_MEASURED
    assert seconds == pytest.approx(15 + 1000 * 0.1 * 4 * 0.20 / 0.12 + 1 * 0.5)
    # a cap below the count it reached (20,000) shortens steps in proportion; one above does not
    capped = estimate_training_seconds(8, 160, 90, 1000, "3dgs", threads=2, measured=run, test_every=0,
                                       max_gaussians=5_000)[0]
    assert capped == pytest.approx(15 + 1000 * 0.1 / 4)
    assert estimate_training_seconds(8, 160, 90, 1000, "3dgs", threads=2, measured=run, test_every=0,
                                     max_gaussians=1_000_000)[0] == pytest.approx(15 + 100)
    # measured with 2 threads, run with 1
    assert estimate_training_seconds(8, 160, 90, 1000, "3dgs", threads=1, measured=run, test_every=0)[0] \
        == pytest.approx(15 + 100 / 0.725)


def test_a_measurement_on_another_backend_is_not_used(tmp_path):
    run = estimate.read_measured_run(write_run(tmp_path / "gpu", backend="cuda"))
    assert estimate_training_seconds(8, 320, 180, 1000, "3dgs", measured=run, backend="cpu")[1] == BASIS_TYPICAL
    assert estimate_training_seconds(8, 320, 180, 1000, "3dgs", measured=run, backend="auto")[1] == BASIS_MEASURED


def test_the_latest_run_is_chosen_one_of_the_same_scene_first(tmp_path):
    scene = write_scene(tmp_path / "scene")
    runs = tmp_path / "runs"
    older = write_run(runs / "older", step_s=0.3, scene=str(scene), mtime=1_000)
    newer = write_run(runs / "newer", step_s=0.2, scene=str(tmp_path / "other"), mtime=2_000)
    write_run(runs / "newest_but_short", steps=10, scene=str(scene), mtime=3_000)
    (runs / "not_a_run").mkdir()
    folders = estimate.run_folders(runs)
    assert {path.name for path in folders} == {"older", "newer", "newest_but_short"}
    assert estimate.latest_measured_run(folders).run_dir == newer
    assert estimate.latest_measured_run(folders, scene).run_dir == older
    assert estimate.latest_measured_run([*folders, newer], tmp_path / "elsewhere").run_dir == newer
    assert estimate.latest_measured_run([]) is None


def test_the_scene_size_and_the_training_size(tmp_path):
    scene = write_scene(tmp_path / "scene", views=5, width=640, height=360)
    assert estimate.scene_image_size(scene) == (5, 640, 360)
    assert estimate.scene_image_size(tmp_path / "nothing") is None
    assert estimate.training_image_size(640, 360, 320) == (320, 180)
    assert estimate.training_image_size(640, 360, 0, 2) == (320, 180)
    assert estimate.training_image_size(640, 360) == (640, 360)


def test_a_run_without_cameras_json_takes_its_scene_size(tmp_path):
    scene = write_scene(tmp_path / "scene", width=640, height=360)
    run = write_run(tmp_path / "run")
    (run / "cameras.json").unlink()
    (run / "config.json").write_text(json.dumps({"scene": str(scene), "method": "3dgs", "width": 320}))
    measured = estimate.read_measured_run(run)
    assert (measured.width, measured.height) == (320, 180)


def test_the_auto_priors_term():
    # 10 s start + per view: NDN 1.5 + SfM 0.1 + fusing 0.1 + stereo labels 4.0 at 320x180
    assert estimate.estimate_priors_seconds(10, 320, 180) == pytest.approx(10 + 10 * 5.7)
    assert estimate.estimate_priors_seconds(10, 320, 180, labels=False) == pytest.approx(10 + 10 * 1.7)
    # the labels shrink images wider than 960 pixels: 1920x1080 costs as 960x540 (9x 320x180)
    assert estimate.estimate_priors_seconds(1, 1920, 1080) == pytest.approx(10 + 1.7 + 4.0 * 9)


def test_durations_are_said_to_an_estimate_s_precision():
    assert estimate.format_estimate(5) == "1 min"
    assert estimate.format_estimate(6 * 60 + 20) == "6 min"
    assert estimate.format_estimate(89 * 60) == "89 min"
    assert estimate.format_estimate(100 * 60) == "1 h 40 min"
    assert estimate.format_estimate(3 * 3600 + 100) == "3 h"


def test_every_shipped_method_has_a_measured_step_cost():
    # a method costed by the fallback would show 3DGS's time in the panel: PGSR's steps cost 2.5x
    from esgs.core.methods import method_names

    assert set(method_names()) <= set(estimate.DEFAULT_STEP_S)
    assert estimate.DEFAULT_STEP_S["pgsr"] > estimate.DEFAULT_STEP_S["esgs"] > estimate.DEFAULT_STEP_S["3dgs"]
