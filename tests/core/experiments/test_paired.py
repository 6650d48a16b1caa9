"""Paired comparisons against a baseline row: differences per scene and seed, verdicts, Markdown."""
from __future__ import annotations

import pytest

from esgs.core.experiments.paired import paired_markdown, paired_rows


def _run(variant, scene, seed, ssim, psnr, lpips, distance):
    return {"variant": variant, "scene": scene, "seed": seed, "ssim": ssim, "psnr": psnr, "lpips": lpips,
            "distance_mean": distance}


RUNS = [
    _run("3DGS", "a_s0", 0, 0.80, 20.0, 0.30, 1.0),
    _run("3DGS", "a_s1", 1, 0.70, 18.0, 0.40, 2.0),
    _run("3DGS", "b_s0", 0, 0.60, 16.0, 0.50, 4.0),
    _run("ESGS", "a_s0", 0, 0.85, 20.5, 0.29, 0.5),
    _run("ESGS", "a_s1", 1, 0.75, 17.0, 0.41, 1.2),
    _run("ESGS", "b_s0", 0, 0.66, 16.6, 0.49, 2.0),
    # no 3DGS run on this scene and seed: left out of the pairs
    _run("ESGS", "c_s0", 0, 0.10, 1.0, 0.90, 9.0),
]


def test_pairs_are_per_scene_and_seed_with_differences_ratios_counts_and_verdicts():
    (row,) = paired_rows(RUNS, "3DGS")
    assert row["variant"] == "ESGS" and row["baseline"] == "3DGS" and row["runs"] == 3
    ssim = row["ssim"]  # +0.05, +0.05, +0.06: better in all three, far beyond the spread
    assert ssim["mean"] == pytest.approx(0.16 / 3) and ssim["n"] == 3 and ssim["better"] == 3
    assert ssim["verdict"] == "better"
    psnr = row["psnr"]  # +0.5, -1.0, +0.6: mean +0.033, std ~0.73: within the spread
    assert psnr["mean"] == pytest.approx(0.1 / 3) and psnr["better"] == 2 and psnr["verdict"] == "within"
    lpips = row["lpips"]  # -0.01, +0.01, -0.01 (lower is better)
    assert lpips["mean"] == pytest.approx(-0.01 / 3) and lpips["better"] == 2 and lpips["verdict"] == "within"
    distance = row["distance_mean"]  # ratios 0.5, 0.6, 0.5
    assert distance["mean"] == pytest.approx(1.6 / 3) and distance["better"] == 3
    assert distance["verdict"] == "better"


def test_worse_beyond_the_spread_and_missing_figures():
    runs = [_run("3DGS", "a", 0, 0.8, 20.0, 0.30, 1.0), _run("3DGS", "b", 1, 0.8, 20.0, 0.30, 1.0),
            _run("X", "a", 0, 0.7, 20.0, 0.40, 2.0), _run("X", "b", 1, 0.6, 20.0, 0.35, 3.0)]
    runs[2]["psnr"] = None  # a missing figure is left out of that metric only
    (row,) = paired_rows(runs, "3DGS")
    assert row["ssim"]["verdict"] == "worse" and row["ssim"]["better"] == 0
    assert row["lpips"]["verdict"] == "worse" and row["distance_mean"]["verdict"] == "worse"
    assert row["psnr"]["n"] == 1 and row["psnr"]["mean"] == 0.0 and row["psnr"]["verdict"] == "within"
    assert paired_rows(runs, "no such row") == [] and paired_rows([], "3DGS") == []


def test_one_run_is_never_beyond_the_spread_and_infinite_or_zero_figures_are_left_out():
    runs = [_run("3DGS", "a", 0, 0.8, 20.0, 0.30, 1.0), _run("X", "a", 0, 0.9, 30.0, 0.10, 0.5)]
    (row,) = paired_rows(runs, "3DGS")
    assert all(row[key]["verdict"] == "within" and row[key]["better"] == 1 for key in ("ssim", "psnr", "lpips",
                                                                                       "distance_mean"))
    runs = [_run("3DGS", "a", 0, 0.8, float("inf"), 0.3, 0.0), _run("3DGS", "b", 1, 0.8, 20.0, 0.3, 1.0),
            _run("X", "a", 0, 0.8, float("inf"), 0.3, 0.5), _run("X", "b", 1, 0.8, 21.0, 0.3, 0.5)]
    (row,) = paired_rows(runs, "3DGS")
    # identical images (PSNR inf) and a baseline on the mesh (distance 0) count nowhere
    assert row["psnr"]["n"] == 1 and row["psnr"]["mean"] == 1.0
    assert row["distance_mean"]["n"] == 1 and row["distance_mean"]["mean"] == 0.5
    assert "inf" not in paired_markdown([row]) and "nan" not in paired_markdown([row])


def test_markdown_marks_better_in_bold_and_worse_in_italics():
    text = paired_markdown(paired_rows(RUNS, "3DGS"))
    lines = text.splitlines()
    assert lines[0] == ("| method | runs | SSIM: difference | PSNR (dB): difference | LPIPS: difference | "
                        "distance (x): ratio |")
    assert lines[2].startswith("| ESGS | 3 | **+0.0533 ± 0.0047 (3/3 better)** | +0.03 ± 0.73 (2/3 better) |")
    assert "**0.533 ± 0.047 (3/3 better)**" in lines[2]
    worse = paired_markdown(paired_rows([_run("3DGS", "a", 0, 0.8, 20, 0.3, 1.0), _run("3DGS", "b", 1, 0.8, 20, 0.3, 1.0),
                                         _run("X", "a", 0, 0.7, 19, 0.4, 2.0), _run("X", "b", 1, 0.7, 19, 0.4, 2.0)],
                                        "3DGS"))
    assert "_-0.1000 ± 0.0000 (0/2 better)_" in worse and "_2.000 ± 0.000 (0/2 better)_" in worse


def test_the_bench_pairs_every_row_with_each_3dgs_row_that_ran_and_prints_the_tables():
    from esgs.core.experiments.bench import METHODS, _comparison, _comparison_markdown

    labels = {method.key: method.label for method in METHODS}
    runs = [{**run, "variant": labels["3dgs_sky"] if run["variant"] == "3DGS" else run["variant"]} for run in RUNS]
    part = _comparison(runs, ["a_s0", "a_s1", "b_s0", "c_s0"], ["ssim", "psnr", "lpips", "distance_mean"])
    # only the defaults' 3DGS ran: one paired table, against it
    assert list(part["paired"]) == [labels["3dgs_sky"]]
    assert part["paired"][labels["3dgs_sky"]] == paired_rows(runs, labels["3dgs_sky"])
    text = "\n".join(_comparison_markdown(part, "At equal step count (4 steps)"))
    assert f"### At equal step count (4 steps): each method against {labels['3dgs_sky']} on the same scene and seed" \
        in text
    assert "| ESGS | 3 | **+0.0533" in text
    both = _comparison(runs + [{**run, "variant": labels["3dgs"]} for run in RUNS if run["variant"] == "3DGS"],
                       ["a_s0"], ["ssim"])
    assert list(both["paired"]) == [labels["3dgs"], labels["3dgs_sky"]]
