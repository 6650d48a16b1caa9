"""benchmarks/time_to_quality.py on finished runs: the target is 3DGS's final evaluation, the
figure the training seconds ESGS's curve takes to reach it, over 3DGS's own."""
from __future__ import annotations

import json

import pytest

from esgs.core.formats.run_dir import RunDir
from tests.conftest import benchmark_script


def _finished_run(folder, curve: list[tuple[int, float, float, float]], gaussians: int) -> None:
    """A run folder as ``esgs train --eval-every K`` leaves it: eval events, then the end's files."""
    run = RunDir(folder)
    run.root.mkdir(parents=True)
    lines = [json.dumps({"kind": "eval", "stage": "eval", "step": step, "total": curve[-1][0],
                         "metrics": {"psnr": psnr, "ssim": ssim, "train_s": seconds}})
             for step, seconds, psnr, ssim in curve[:-1]]
    run.events.write_text("\n".join(lines) + "\n", encoding="utf-8")
    step, seconds, psnr, ssim = curve[-1]
    run.metrics.write_text(json.dumps({"step": step, "psnr": psnr, "ssim": ssim}), encoding="utf-8")
    run.result.write_text(json.dumps({"step": step, "train_s": seconds, "elapsed_s": seconds + 5,
                                      "n_gaussians": gaussians}), encoding="utf-8")


def test_the_ratio_comes_from_the_esgs_curve_crossing_3dgs_final_quality(tmp_path):
    _finished_run(tmp_path / "runs" / "3dgs", [(100, 10.0, 20.0, 0.5), (200, 20.0, 30.0, 0.8)], 1000)
    # ESGS crosses 30 dB halfway between 10 and 14 s (28 -> 32 dB), its SSIM 0.8 at 14 s
    _finished_run(tmp_path / "runs" / "esgs", [(100, 10.0, 28.0, 0.7), (200, 14.0, 32.0, 0.8),
                                              (300, 18.0, 33.0, 0.9)], 1200)
    out = tmp_path / "report.json"
    with benchmark_script("time_to_quality") as script:
        assert script.main([str(tmp_path / "scene"), "--out", str(tmp_path / "runs"), "--json", str(out)]) == 0
    report = json.loads(out.read_text(encoding="utf-8"))
    assert report["target"] == {"psnr": 30.0, "ssim": 0.8, "3dgs_train_s": 20.0}
    assert report["esgs_to_psnr_s"] == pytest.approx(12.0)
    assert report["esgs_to_ssim_s"] == pytest.approx(14.0)
    assert report["ratio_to_3dgs_train_s"] == pytest.approx(14.0 / 20.0)
    assert report["arms"]["esgs"]["gaussians"] == 1200 and report["arms"]["3dgs"]["reused"]
    assert [point["step"] for point in report["arms"]["esgs"]["curve"]] == [100, 200, 300]


def test_a_run_that_never_reaches_the_target_has_no_ratio(tmp_path):
    _finished_run(tmp_path / "runs" / "3dgs", [(100, 10.0, 30.0, 0.8)], 1000)
    _finished_run(tmp_path / "runs" / "esgs", [(100, 10.0, 29.0, 0.9)], 1000)
    out = tmp_path / "report.json"
    with benchmark_script("time_to_quality") as script:
        script.main([str(tmp_path / "scene"), "--out", str(tmp_path / "runs"), "--json", str(out)])
    report = json.loads(out.read_text(encoding="utf-8"))
    assert report["esgs_to_both_s"] is None and report["ratio_to_3dgs_train_s"] is None
