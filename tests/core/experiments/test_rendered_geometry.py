"""benchmarks/rendered_geometry.py: a run's rendered depth and normals against the exact maps."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.core.experiments.helpers import load_benchmark_script


def _write_model(run, gaussians: dict) -> None:
    """Replace a run's Gaussians with ``gaussians`` (tensors as tests.core.train.scene makes them)."""
    from esgs.core.formats.ply import GaussianPly, write_gaussians_ply
    from esgs.core.formats.run_dir import RunDir
    from esgs.core.train.gaussians import rgb_to_sh_dc

    count = gaussians["means"].shape[0]
    write_gaussians_ply(RunDir(run).point_cloud, GaussianPly(
        means=gaussians["means"], normals=np.zeros((count, 3)), sh_dc=rgb_to_sh_dc(gaussians["colors"]),
        sh_rest=np.zeros((count, 0, 3)), opacity_logit=torch.logit(gaussians["opacities"]),
        log_scales=torch.log(gaussians["scales"]), quats_wxyz=gaussians["quats"]))


def test_the_true_gaussians_score_no_error_and_tilted_ones_score_their_tilt(tmp_path):
    from esgs.core.train import TrainConfig, train
    from tests.core.methods.test_esgs_hooks import _write_gt_priors
    from tests.core.train.scene import ground_truth_gaussians, make_scene

    script = load_benchmark_script("rendered_geometry")
    scene = make_scene(tmp_path / "scene", views=6, width=32, height=24)
    _write_gt_priors(scene)  # rendered from ground_truth_gaussians(14, 0)
    run = tmp_path / "run"
    train(TrainConfig(scene=str(scene), out=str(run), iterations=2, backend="cpu", lpips=False, test_every=3,
                      mask_source="none", save_renders=False, checkpoint_every=0, densify_until=0, sh_degree=0,
                      sky="none"))
    truth = ground_truth_gaussians(14, 0)
    _write_model(run, truth)
    exact = script.run_scores(run, scene)
    assert exact["pixels"] > 500
    assert exact["abs_rel"] < 1e-3 and exact["delta1"] == pytest.approx(1.0)
    assert exact["normal_mean_deg"] < 1.0 and exact["normal_within_11_25"] == pytest.approx(1.0)
    # every Gaussian tilted by 20 degrees about x: the normals are 20 degrees off wherever drawn
    angle = math.radians(20.0)
    tilted = dict(truth, quats=torch.tensor([[math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0]]).expand(
        truth["means"].shape[0], 4).contiguous())
    _write_model(run, tilted)
    off = script.run_scores(run, scene)
    assert off["normal_mean_deg"] == pytest.approx(20.0, abs=2.0)
    assert off["normal_within_11_25"] < 0.05


def test_runs_are_named_from_a_study_folder_a_folder_of_seeds_or_one_run(tmp_path):
    import json

    script = load_benchmark_script("rendered_geometry")
    study = tmp_path / "study"
    (study / "work" / "run001").mkdir(parents=True)
    (study / "rows.json").write_text(json.dumps({"rows": [
        {"index": 1, "name": "scene/arm/cpu/seed4", "group": "scene", "arm": "arm", "seed": 4}]}))
    seeds = tmp_path / "seeds"
    for seed in (2, 0):
        (seeds / f"seed{seed}").mkdir(parents=True)
        (seeds / f"seed{seed}" / "config.json").write_text(json.dumps({"seed": seed}))
    (seeds / "notes").mkdir()  # not a run: skipped
    assert script._runs(str(study)) == [({"name": "scene/arm/cpu/seed4", "group": "scene", "arm": "arm", "seed": 4},
                                         study / "work" / "run001")]
    assert script._runs(f"mixed/3dgs={seeds}") == [
        ({"name": "mixed/3dgs/seed0", "group": "mixed", "arm": "3dgs", "seed": 0}, seeds / "seed0"),
        ({"name": "mixed/3dgs/seed2", "group": "mixed", "arm": "3dgs", "seed": 2}, seeds / "seed2")]
    assert script._runs(f"mixed/one={seeds / 'seed2'}") == [
        ({"name": "mixed/one", "group": "mixed", "arm": "one", "seed": None}, seeds / "seed2")]
