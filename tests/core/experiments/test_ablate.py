"""esgs ablate on a tiny scene: the grid, prior and K studies, tables, restart without retraining."""
from __future__ import annotations

import json
import math

import pytest

from esgs.core.errors import ConfigError, DatasetError
from esgs.core.experiments.ablate import ablation_variants, plan_ablation, run_ablation
from esgs.core.experiments.tables import mean_std

from .helpers import make_experiment_scene

TRAIN = {"backend": "cpu", "threads": 1, "lpips": False, "densify_until": 0, "test_every": 3, "save_renders": False,
         "checkpoint_every": 0, "sh_degree": 1,
         "init_opacity": 0.7}  # opaque from the start, so the opacity >= 0.5 distance filter keeps centres


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_experiment_scene(tmp_path_factory.mktemp("ablate") / "scene")


def test_variants_follow_the_paper_and_share_identical_runs(scene, tmp_path):
    variants = ablation_variants(scene)
    grid = [(v.label, v.key) for v in variants if v.study == "grid"]
    assert grid == [("3DGS", "3dgs"), ("+depth", "depth-gt"), ("+normal", "normal-gt"),
                    ("+depth+normal", "depth-normal-gt"), ("+all (depth+normal+GPDFN)", "depth-normal-gpdfn3-gt")]
    assert [v.label for v in variants if v.study == "priors"] == ["3DGS", "none", "gt"]
    k_keys = [v.key for v in variants if v.study == "fused_k"]
    assert k_keys[0] == "depth-normal-gt" and k_keys[2] == "depth-normal-gpdfn3-gt" and len(k_keys) == 5
    _, tasks = plan_ablation(scene, tmp_path, iterations=10, seeds=[0, 1])
    # 3dgs, depth, normal, depth+normal, K=2..5 with priors, GPDFN without priors: 9 variants x 2 seeds
    assert len(tasks) == 18 and len({task.out for task in tasks}) == 18
    with pytest.raises(DatasetError, match="labels"):
        ablation_variants(scene, priors="labels")


def test_studies_can_be_chosen_and_the_prior_study_has_the_3dgs_baseline(scene, tmp_path):
    variants = ablation_variants(scene, studies=["priors"])
    assert {v.study for v in variants} == {"priors"}
    assert [(v.label, v.key) for v in variants] == [("3DGS", "3dgs"), ("none", "gpdfn3"), ("gt", "depth-normal-gpdfn3-gt")]
    _, tasks = plan_ablation(scene, tmp_path, iterations=10, seeds=[0, 1, 2], studies=["priors"])
    assert sorted(task.name for task in tasks)[:3] == ["3dgs/seed0", "3dgs/seed1", "3dgs/seed2"] and len(tasks) == 9
    with pytest.raises(ConfigError, match="fused"):
        ablation_variants(scene, studies=["fused"])


def test_mean_std_over_seeds():
    stats = mean_std([1.0, 3.0, None])
    assert stats == {"mean": 2.0, "std": 1.0, "n": 2}
    assert mean_std([None])["mean"] is None


def test_ablation_runs_writes_tables_and_skips_finished_runs_on_restart(scene, tmp_path):
    out = tmp_path / "ablation"
    statuses = []
    table = run_ablation(scene, out, iterations=4, seeds=[0, 1], fused_ks=[1, 3], train=TRAIN,
                         on_run=lambda task, status: statuses.append(status))
    assert table["failed"] == [] and statuses.count("trained") == 12
    grid = table["studies"]["grid"]
    assert [row["variant"] for row in grid][0] == "3DGS"
    for row in grid:
        assert row["seeds"] == [0, 1]
        for key in ("psnr", "ssim", "distance_mean", "distance_std"):
            assert row[key]["n"] == 2 and math.isfinite(row[key]["mean"])
    # the table's numbers are the mean of the runs' own summaries
    runs = [json.loads((out / "runs" / "3dgs" / f"seed{s}" / "summary.json").read_text()) for s in (0, 1)]
    assert grid[0]["psnr"]["mean"] == pytest.approx((runs[0]["psnr"] + runs[1]["psnr"]) / 2)
    assert runs[0]["distance_mean"] > 0
    saved = json.loads((out / "ablation.json").read_text())
    assert saved["studies"]["fused_k"][0]["run"] == "depth-normal-gt"
    markdown = (out / "ablation.md").read_text()
    assert "## Ablation grid" in markdown and "| +depth+normal |" in markdown and "K=3" in markdown
    # a restart trains nothing and gives the same table
    statuses.clear()
    again = run_ablation(scene, out, iterations=4, seeds=[0, 1], fused_ks=[1, 3], train=TRAIN,
                         on_run=lambda task, status: statuses.append(status))
    assert statuses == ["skipped"] * 12
    assert again["studies"] == json.loads(json.dumps(table["studies"]))


def test_ablate_command_runs_the_priors_none_grid_and_reports(scene, tmp_path, capsys):
    from esgs.core.cli import main

    out = tmp_path / "cli"
    code = main(["ablate", str(scene), "--out", str(out), "--iterations", "2", "--priors", "none", "--fused-k", "3",
                 "--backend", "cpu", "--threads", "1", "--no-lpips", "--studies", "grid,priors"])
    assert code == 0
    table = json.loads((out / "ablation.json").read_text())
    # without priors: 3DGS and GPDFN only, in every study
    assert [row["run"] for row in table["studies"]["grid"]] == ["3dgs", "gpdfn3"]
    assert list(table["studies"]) == ["grid", "priors"]
    assert {row["run"] for row in table["studies"]["priors"]} == {"3dgs", "gpdfn3", "depth-normal-gpdfn3-gt"}
    assert "wrote" in capsys.readouterr().out
