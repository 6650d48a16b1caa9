"""benchmarks/memory_timeline.py: the per-step memory records and their summary."""
from __future__ import annotations

import json
import sys

import pytest

from tests.conftest import benchmark_script


@pytest.fixture(scope="module")
def timeline():
    with benchmark_script("memory_timeline") as module:
        yield module


def test_the_summary_finds_the_peak_and_where_it_sits(timeline):
    lines = [{"setup_peak_mib": 400.0, "gaussians": 100},
             {"step": 1, "gaussians_before": 100, "gaussians": 100, "rss_mib": 450.0, "peak_mib": 480.0},
             {"step": 2, "gaussians_before": 100, "gaussians": 300, "rss_mib": 500.0, "peak_mib": 650.0},
             {"step": 3, "gaussians_before": 300, "gaussians": 250, "rss_mib": 505.0, "peak_mib": 560.0},
             {"end_peak_mib": 520.0}]
    result = timeline.summarise(lines, floor_mib=200.0, every=2)
    assert result["peak_mib"] == 650.0 and result["peak_above_floor_mib"] == 450.0
    assert result["peak_step"] == 2 and result["gaussians_at_peak_step"] == 300 and result["max_gaussians"] == 300
    assert result["bytes_above_floor_per_gaussian_at_max"] == pytest.approx(450.0 * 2**20 / 300)
    assert result["densifying_steps"] == 2 and result["steps"] == 3
    assert [line["step"] for line in result["timeline"]] == [2]  # every 2nd step, the peak's included
    # a set-up or an end of run above every step is the peak
    assert timeline.summarise(lines[:-1] + [{"end_peak_mib": 900.0}], 200.0)["peak_mib"] == 900.0
    with pytest.raises(SystemExit, match="no training step"):
        timeline.summarise(lines[:1], 200.0)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_short_run_records_every_step_and_a_peak_above_the_floor(timeline, tiny_scene, tmp_path):
    out = tmp_path / "figures.json"
    code = timeline.main(["--json", str(out), "--every", "1", "--", "train", str(tiny_scene), "--out",
                          str(tmp_path / "run"), "--iterations", "4", "--threads", "1", "--checkpoint-every", "0",
                          "--no-evaluate", "--quiet"])
    assert code == 0
    result = json.loads(out.read_text())
    assert result["steps"] == 4 and [line["step"] for line in result["timeline"]] == [1, 2, 3, 4]
    assert all(line["peak_mib"] >= line["rss_mib"] > 0 for line in result["timeline"])
    assert result["peak_mib"] >= max(line["peak_mib"] for line in result["timeline"])
    assert 100.0 < result["floor_mib"] < result["peak_mib"]
    assert (tmp_path / "run" / "point_cloud.ply").is_file()
