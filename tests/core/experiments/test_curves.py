"""Evaluation curves of runs and the time to reach a quality (esgs.core.experiments.curves)."""
from __future__ import annotations

import json

import pytest

from esgs.core.experiments.curves import EvalPoint, read_eval_curve, time_to_reach

CURVE = [EvalPoint(10, 1.0, 20.0, 0.50), EvalPoint(20, 2.0, 22.0, 0.60), EvalPoint(30, 3.0, 25.0, 0.70),
         EvalPoint(40, 4.0, 24.0, 0.80)]


def test_an_exact_crossing_is_the_evaluation_time():
    assert time_to_reach(CURVE, psnr=22.0) == pytest.approx(2.0)
    assert time_to_reach(CURVE, ssim=0.7) == pytest.approx(3.0)


def test_a_crossing_between_evaluations_is_interpolated():
    assert time_to_reach(CURVE, psnr=23.5) == pytest.approx(2.5)
    assert time_to_reach(CURVE, ssim=0.55) == pytest.approx(1.5)
    assert time_to_reach(CURVE, ssim=0.75) == pytest.approx(3.5)


def test_the_first_time_counts_even_when_the_curve_drops_later():
    assert time_to_reach(CURVE, psnr=24.5) == pytest.approx(2.0 + 2.5 / 3.0)


def test_never_reached_is_none():
    assert time_to_reach(CURVE, psnr=25.5) is None
    assert time_to_reach(CURVE, ssim=0.9) is None
    assert time_to_reach([], psnr=10.0) is None
    assert time_to_reach(CURVE, psnr=21.0, ssim=0.95) is None  # one target missed: not reached


def test_both_targets_take_the_later_time():
    assert time_to_reach(CURVE, psnr=21.0, ssim=0.65) == pytest.approx(2.5)  # psnr at 1.5 s, ssim at 2.5 s
    assert time_to_reach(CURVE, psnr=24.0, ssim=0.55) == pytest.approx(2.0 + 2.0 / 3.0)


def test_reached_at_the_first_evaluation_counts_at_its_time():
    assert time_to_reach(CURVE, psnr=15.0) == pytest.approx(1.0)


def test_missing_values_are_skipped_and_a_target_is_needed():
    curve = [EvalPoint(1, 1.0, None, 0.2), EvalPoint(2, 2.0, 10.0, 0.4), EvalPoint(3, 3.0, 20.0, None)]
    assert time_to_reach(curve, psnr=15.0) == pytest.approx(2.5)
    assert time_to_reach(curve, ssim=0.3) == pytest.approx(1.5)
    with pytest.raises(ValueError):
        time_to_reach(curve)


def _event(step, train_s, psnr, ssim, kind="eval"):
    return json.dumps({"step": step, "total": 40, "stage": "eval", "kind": kind, "message": "", "time": 0.0,
                       "metrics": {"psnr": psnr, "ssim": ssim, "train_s": train_s, "n_gaussians": 5}})


def test_read_the_curve_of_a_run_folder(tmp_path):
    lines = [_event(10, 1.0, 20.0, 0.5), _event(20, 2.0, 22.0, 0.6, kind="progress"), _event(20, 2.5, 21.0, 0.6),
             # a session resumed from the checkpoint at step 10 trains 11.. again: its points replace the others
             _event(20, 2.2, 21.5, 0.62), '{"torn', _event(30, 3.1, 23.0, 0.7)]
    (tmp_path / "events.jsonl").write_text("\n".join(lines) + "\n")
    (tmp_path / "metrics.json").write_text(json.dumps({"psnr": 24.0, "ssim": 0.75, "step": 40}))
    (tmp_path / "train_result.json").write_text(json.dumps({"step": 40, "elapsed_s": 9.0, "train_s": 4.0}))
    assert read_eval_curve(tmp_path) == [EvalPoint(10, 1.0, 20.0, 0.5), EvalPoint(20, 2.2, 21.5, 0.62),
                                         EvalPoint(30, 3.1, 23.0, 0.7), EvalPoint(40, 4.0, 24.0, 0.75)]


def test_the_final_evaluation_event_is_not_counted_twice_and_older_runs_give_their_last_point(tmp_path):
    (tmp_path / "events.jsonl").write_text(_event(40, 4.0, 24.0, 0.75) + "\n")
    (tmp_path / "metrics.json").write_text(json.dumps({"psnr": 24.0, "ssim": 0.75, "step": 40}))
    (tmp_path / "train_result.json").write_text(json.dumps({"step": 40, "elapsed_s": 9.0, "train_s": 4.0}))
    assert read_eval_curve(tmp_path) == [EvalPoint(40, 4.0, 24.0, 0.75)]
    older = tmp_path / "older"
    older.mkdir()
    (older / "metrics.json").write_text(json.dumps({"psnr": 24.0, "ssim": 0.75, "step": 40}))
    (older / "train_result.json").write_text(json.dumps({"step": 40, "elapsed_s": 9.0}))
    assert read_eval_curve(older) == [EvalPoint(40, 9.0, 24.0, 0.75)]
    assert read_eval_curve(tmp_path / "missing") == []


def test_a_trained_run_gives_its_curve(tmp_path):
    from esgs.core.train import TrainConfig, train

    from .helpers import make_experiment_scene

    scene = make_experiment_scene(tmp_path / "scene")
    result = train(TrainConfig(scene=scene, out=tmp_path / "run", iterations=6, eval_every=2, backend="cpu",
                               threads=1, lpips=False, test_every=3, save_renders=False, checkpoint_every=0,
                               densify_until=0, sh_degree=1))
    curve = read_eval_curve(result.run_dir)
    assert [point.step for point in curve] == [2, 4, 6]
    assert curve[-1].train_s == pytest.approx(result.train_s)
    assert curve[-1].psnr == pytest.approx(result.metrics["psnr"])
    assert time_to_reach(curve, psnr=curve[-1].psnr) <= result.train_s


def _run(key, scene, seed, *points):
    return {"key": key, "variant": key.upper(), "scene": scene, "seed": seed,
            "curve": [EvalPoint(10 * (i + 1), *point) for i, point in enumerate(points)]}


def test_time_to_the_baseline_quality_per_run_and_per_method():
    from esgs.core.experiments.curves import time_to_baseline_quality

    runs = [_run("3dgs", "a", 0, (2.0, 20.0, 0.6), (4.0, 24.0, 0.7)),
            _run("esgs", "a", 0, (1.0, 22.0, 0.65), (2.0, 26.0, 0.75), (3.0, 27.0, 0.8)),
            _run("3dgs", "b", 1, (2.0, 20.0, 0.6), (5.0, 21.0, 0.8)),
            _run("esgs", "b", 1, (2.0, 20.0, 0.6), (4.0, 22.0, 0.7)),  # never reaches SSIM 0.8
            _run("esgs", "c", 0, (1.0, 30.0, 0.9))]  # no 3DGS run on c
    figures = time_to_baseline_quality(runs, "3dgs")
    records = {(r["key"], r["scene"]): r for r in figures["runs"]}
    a = records[("esgs", "a")]
    assert (a["target_psnr"], a["target_ssim"], a["baseline_s"]) == (24.0, 0.7, 4.0)
    assert a["to_psnr_s"] == pytest.approx(1.5) and a["to_ssim_s"] == pytest.approx(1.5)
    assert a["to_quality_s"] == pytest.approx(1.5) and a["ratio"] == pytest.approx(1.5 / 4.0)
    assert records[("3dgs", "a")]["to_quality_s"] == pytest.approx(4.0) and records[("3dgs", "a")]["ratio"] == 1.0
    b = records[("esgs", "b")]
    assert b["to_psnr_s"] == pytest.approx(3.0)  # 20 dB at 2 s, 22 dB at 4 s: 21 dB at 3 s
    assert b["to_ssim_s"] is None and b["to_quality_s"] is None and b["ratio"] is None
    assert figures["missing_baseline"] == ["c seed 0"] and ("esgs", "c") not in records
    overall = {row["variant"]: row for row in figures["overall"]}
    assert overall["ESGS"]["runs"] == 2 and overall["ESGS"]["reached"] == 1
    assert overall["ESGS"]["to_quality_s"]["n"] == 1 and overall["ESGS"]["to_quality_s"]["mean"] == pytest.approx(1.5)
    assert overall["ESGS"]["to_psnr_s"]["n"] == 2
    assert overall["3DGS"]["reached"] == 2 and overall["3DGS"]["ratio"]["mean"] == pytest.approx(1.0)
    assert list(figures["per_scene"]) == ["a", "b"]
    assert [row["variant"] for row in figures["per_scene"]["b"]] == ["3DGS", "ESGS"]
