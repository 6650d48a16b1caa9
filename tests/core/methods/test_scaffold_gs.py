"""Scaffold-GS: voxel anchors, decoding, growing and pruning, the volume term, export and short runs."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from esgs.core.errors import ConfigError
from esgs.core.methods import ScaffoldGSConfig, get_method, make_trainer, train
from esgs.core.methods.baselines.scaffold_gs import (ScaffoldDecoder, ScaffoldHook, ScaffoldStrategy, camera_centre,
                                                     decode_anchors, decoded_model, grow_anchors, prune_anchors,
                                                     visible_anchors, volume_regulariser, voxel_size_from_points,
                                                     voxelise)
from esgs.core.train.checkpoint import latest_checkpoint, list_checkpoints, load_checkpoint
from esgs.core.train.config import TrainConfig
from esgs.core.train.hooks import TrainHook
from tests.core.train.scene import make_scene


# --- anchors from points ----------------------------------------------------------------
def test_voxelise_puts_one_anchor_at_the_centre_of_every_occupied_voxel():
    points = torch.tensor([[0.04, 0.0, 0.0],     # voxel (0, 0, 0)
                           [-0.04, 0.02, 0.01],  # voxel (0, 0, 0) again
                           [0.26, 0.0, 0.0],     # round(2.6) = 3 -> (3, 0, 0)
                           [0.0, -0.16, 0.5],    # (0, -2, 5)
                           [0.31, 0.04, -0.04]])  # (3, 0, 0) again
    centres = voxelise(points, 0.1)
    expected = torch.tensor([[0.0, -0.2, 0.5], [0.0, 0.0, 0.0], [0.3, 0.0, 0.0]])  # lexicographic voxel order
    torch.testing.assert_close(centres, expected)


def test_voxel_size_is_the_median_nearest_neighbour_distance():
    # a row of points 0.1 apart and one 0.5 from its neighbour: distances 0.1 x 4 and 0.5 -> median 0.1
    points = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0], [0.8, 0, 0], [0.8, 0, 0]])
    assert voxel_size_from_points(points) == pytest.approx(0.1)  # the duplicate (distance 0) is left out
    assert voxel_size_from_points(np.zeros((1, 3))) == pytest.approx(0.01)


# --- decoding ----------------------------------------------------------------------------
def _anchors(count: int = 6, k: int = 4, features: int = 8, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    positions = torch.randn(count, 3, generator=generator)
    return (positions, 0.5 * torch.randn(count, features, generator=generator),
            0.3 * torch.randn(count, k, 3, generator=generator),
            math.log(0.2) + 0.1 * torch.randn(count, 6, generator=generator))


def test_decoding_is_deterministic_and_follows_the_definitions():
    positions, features, offsets, log_scaling = _anchors()
    camera = torch.tensor([0.5, -1.0, 4.0])
    first = decode_anchors(positions, features, offsets, log_scaling, ScaffoldDecoder(8, 4, seed=3), camera, extent=2.0)
    again = decode_anchors(positions, features, offsets, log_scaling, ScaffoldDecoder(8, 4, seed=3), camera, extent=2.0)
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.equal(getattr(first.params, name), getattr(again.params, name)), name
    assert torch.equal(first.slots, again.slots)
    other = decode_anchors(positions, features, offsets, log_scaling, ScaffoldDecoder(8, 4, seed=4), camera, extent=2.0)
    assert not torch.equal(first.opacity, other.opacity)

    # the definitions, for every Gaussian kept: centre, scale, opacity > 0, unit quaternion
    decoder = ScaffoldDecoder(8, 4, seed=3)
    relative = positions - camera
    distance = relative.norm(dim=-1, keepdim=True)
    opacity, colour, factors, quats = decoder(features, relative / distance, distance / 2.0)
    scaling = torch.exp(log_scaling)
    means = (positions[:, None] + offsets * scaling[:, None, :3]).reshape(-1, 3)
    kept = opacity.reshape(-1) > 0
    assert 0 < int(kept.sum()) < kept.numel()  # some are dropped (tanh of random outputs)
    torch.testing.assert_close(first.params.means, means[kept])
    torch.testing.assert_close(first.params.scales, (scaling[:, None, 3:] * factors).reshape(-1, 3)[kept])
    torch.testing.assert_close(first.params.opacities, opacity.reshape(-1)[kept])
    torch.testing.assert_close(first.params.quats.norm(dim=-1), torch.ones(int(kept.sum())))
    from esgs.core.train.gaussians import sh_dc_to_rgb

    torch.testing.assert_close(sh_dc_to_rgb(first.params.colors[:, 0]), colour.reshape(-1, 3)[kept])
    assert first.params.sh_degree == 0 and (first.params.opacities > 0).all()
    assert torch.equal(first.slots, torch.nonzero(kept).reshape(-1))  # anchor * k + offset


def test_decoding_depends_on_the_view_and_is_differentiable():
    positions, features, offsets, log_scaling = _anchors()
    features.requires_grad_(True)
    offsets.requires_grad_(True)
    decoder = ScaffoldDecoder(8, 4, seed=0)
    near = decode_anchors(positions, features, offsets, log_scaling, decoder, torch.tensor([0.0, 0.0, 3.0]))
    far = decode_anchors(positions, features, offsets, log_scaling, decoder, torch.tensor([3.0, 0.0, 0.0]))
    assert not torch.equal(near.opacity, far.opacity)
    (near.params.means.sum() + near.params.opacities.sum() + near.params.colors.sum()).backward()
    assert features.grad.abs().sum() > 0 and offsets.grad.abs().sum() > 0
    # one camera per anchor: each anchor decoded as for that camera alone
    centres = torch.tensor([[0.0, 0.0, 3.0], [3.0, 0.0, 0.0]]).repeat(3, 1)
    mixed = decode_anchors(positions, features, offsets, log_scaling, decoder, centres)
    torch.testing.assert_close(mixed.opacity[0::2], near.opacity[0::2])
    torch.testing.assert_close(mixed.opacity[1::2], far.opacity[1::2])


def test_visible_anchors_are_those_whose_sphere_reaches_the_image():
    viewmat = torch.eye(4)  # camera at the origin looking along +z
    K = torch.tensor([[10.0, 0.0, 10.0], [0.0, 10.0, 10.0], [0.0, 0.0, 1.0]])
    positions = torch.tensor([[0.0, 0.0, 1.0],    # centre of the image
                              [0.0, 0.0, -1.0],   # behind
                              [1.5, 0.0, 1.0],    # u = 25 > 20, sphere radius 0.1 m -> 1 px: not visible
                              [1.05, 0.0, 1.0]])  # u = 20.5, within a pixel of the border: visible
    offsets = torch.zeros(4, 2, 3)
    log_scaling = torch.full((4, 6), math.log(0.1 / 3.0))  # 3 x the Gaussian scale = 0.1
    assert visible_anchors(positions, offsets, log_scaling, viewmat, K, 20, 20).tolist() == [True, False, False, True]
    torch.testing.assert_close(camera_centre(torch.tensor([[1.0, 0, 0, -1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])),
                               torch.tensor([1.0, -2.0, -3.0]))


def test_the_ply_export_round_trips(tmp_path):
    from esgs.core.formats.ply import read_gaussians_ply, write_gaussians_ply
    from esgs.core.train.gaussians import GaussianModel

    positions, features, offsets, log_scaling = _anchors(count=20)
    decoded = decode_anchors(positions, features, offsets, log_scaling, ScaffoldDecoder(8, 4, seed=1),
                             torch.tensor([0.0, 0.0, 5.0]))
    model = decoded_model(decoded.params, 3)
    assert len(model) == decoded.slots.numel() and model.max_sh_degree == 3
    write_gaussians_ply(tmp_path / "point_cloud.ply", model.to_ply())
    back = GaussianModel.from_ply(read_gaussians_ply(tmp_path / "point_cloud.ply"))
    assert back.max_sh_degree == 3
    for name, value in model.params.items():
        torch.testing.assert_close(back.params[name], value.detach(), rtol=0, atol=0, msg=name)
    # and the activations are the decoded Gaussians'
    torch.testing.assert_close(back.opacities(), decoded.params.opacities, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(back.scales(), decoded.params.scales, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(back.unit_quats(), decoded.params.quats)
    torch.testing.assert_close(back.sh_coefficients()[:, :1], decoded.params.colors)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_export_stays_on_the_decoding_device():
    # the first CUDA run failed at evaluation: the export's zero higher SH bands were made on the CPU
    positions, features, offsets, log_scaling = (t.cuda() for t in _anchors(count=20))
    decoded = decode_anchors(positions, features, offsets, log_scaling, ScaffoldDecoder(8, 4, seed=1).cuda(),
                             torch.tensor([0.0, 0.0, 5.0], device="cuda"))
    model = decoded_model(decoded.params, 3)
    assert {value.device.type for value in model.params.values()} == {"cuda"}
    assert model.render_params(3).colors.device.type == "cuda"


# --- the volume regulariser --------------------------------------------------------------
def test_volume_regulariser_by_hand_and_by_finite_differences():
    scales = torch.tensor([[1.0, 2.0, 3.0], [0.5, 0.5, 4.0]], dtype=torch.float64)
    assert float(volume_regulariser(scales)) == pytest.approx((6.0 + 1.0) / 2)
    assert float(volume_regulariser(torch.zeros(0, 3))) == 0.0
    scales = (torch.rand(5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) + 0.1).requires_grad_()
    assert torch.autograd.gradcheck(volume_regulariser, (scales,))


# --- growing and pruning ---------------------------------------------------------------
def test_growing_on_hand_made_statistics():
    anchors = torch.tensor([[0.0, 0.0, 0.0]])
    # four neural Gaussians of anchor 0 (k = 4), voxel size 1, two levels: edges 4 and 1
    gaussians = torch.tensor([[0.3, 0.0, 0.0],    # in the anchor's own voxel at both levels: nothing
                              [1.2, 0.0, 0.0],    # level 1 voxel (1, 0, 0), free; level 0 voxel (0,0,0) taken
                              [9.0, 0.0, 0.0],    # level 0 voxel (2, 0, 0) at edge 4 -> centre (8, 0, 0)
                              [1.1, 0.2, -0.1]])  # same level-1 voxel as the second, but never observed
    gradients = torch.tensor([1.0, 0.3, 0.15, 1.0])
    observed = torch.tensor([True, True, True, False])
    growth = grow_anchors(anchors, gaussians, gradients, observed, voxel_size=1.0, threshold=0.1, levels=2)
    # level 0 (edge 4, threshold 0.1): Gaussians 0, 1, 2 significant; only (2, 0, 0) is free -> (8, 0, 0)
    # level 1 (edge 1, threshold 0.2): Gaussians 0, 1; (1, 0, 0) is free -> (1, 0, 0); Gaussian 2 too weak
    torch.testing.assert_close(growth.positions, torch.tensor([[8.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    torch.testing.assert_close(growth.voxel_sizes, torch.tensor([4.0, 1.0]))
    assert growth.members.tolist() == [2, 1] and growth.member_anchor.tolist() == [0, 1]
    # nothing significant, nothing grown
    assert len(grow_anchors(anchors, gaussians, gradients * 0.01, observed, voxel_size=1.0, threshold=0.1,
                            levels=2).positions) == 0
    # random elimination: a seeded subset of the free voxels, the same for the same seed
    many = torch.stack([torch.arange(40.0) * 2.0 + 5.0, torch.zeros(40), torch.zeros(40)], dim=1)
    kept = [grow_anchors(anchors, many, torch.ones(40), torch.ones(40, dtype=torch.bool), voxel_size=1.0, threshold=0.1,
                         levels=1, generator=torch.Generator().manual_seed(seed)).positions for seed in (0, 0, 1)]
    assert 5 < len(kept[0]) < 40 and torch.equal(kept[0], kept[1]) and not torch.equal(kept[0], kept[2])


def test_pruning_on_hand_made_statistics():
    # summed opacity over the k Gaussians and the steps seen; threshold 0.005 per step; judged after > 8 steps
    opacity = torch.tensor([0.01, 0.5, 0.0, 0.001])
    visits = torch.tensor([10.0, 10.0, 3.0, 9.0])
    prune = prune_anchors(opacity, visits, min_opacity=0.005, min_visits=8)
    assert prune.tolist() == [True, False, False, True]  # the third is too rarely seen to be judged


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("scaffold") / "scene", views=6, width=32, height=24)


def _config(scene, out, **overrides) -> TrainConfig:
    settings = {key: overrides.pop(key) for key in list(overrides) if key.startswith("scaffold_")}
    values = dict(scene=scene, out=out, iterations=60, backend="cpu", threads=1, evaluate=True, lpips=False,
                  test_every=3, save_renders=False, checkpoint_every=0, progress_every=20, method="scaffold-gs",
                  method_config=ScaffoldGSConfig(**settings))
    values.update(overrides)
    return TrainConfig(**values)


def test_the_strategy_grows_and_prunes_anchors_with_their_optimizer_state(scene, tmp_path):
    trainer = make_trainer(_config(scene, tmp_path / "run", scaffold_offsets=2, scaffold_grow_levels=1))
    trainer._start_run_dir(None)
    trainer.setup()
    strategy = trainer.strategy
    assert isinstance(strategy, ScaffoldStrategy)
    trainer.train_step(1)  # Adam moments exist
    count = len(trainer.gaussians)
    every = strategy.schedule.densify_every
    with torch.no_grad():
        strategy.gradient_accum.zero_()
        strategy.gaussian_visits.fill_(every)  # everything judged
        strategy.gradient_accum[1] = every * 1.0  # anchor 0's second Gaussian: large gradient
        strategy.offsets[0, 1] = torch.tensor([0.0, 0.0, 40.0])  # ... far above the plane, in a free voxel
        strategy.anchor_visits.fill_(every)
        strategy.opacity_accum.fill_(every)
        strategy.opacity_accum[3] = 0.0  # anchor 3: transparent, pruned
    target = trainer.gaussians.params["means"][0] + strategy.offsets[0, 1] * torch.exp(strategy.log_scaling[0, :3])
    features = strategy.features.detach().clone()
    import dataclasses

    strategy.context = dataclasses.replace(strategy.context, generator=None)  # no random elimination
    report = strategy.update(step=100)
    assert (report.count_before, report.count_after, report.cloned, report.pruned) == (count, count, 1, 1)
    grown = trainer.gaussians.params["means"][-1]
    assert float((grown - target).abs().max()) <= strategy.voxel_size / 2 + 1e-6  # the centre of its voxel
    torch.testing.assert_close(strategy.features[-1], features[0])  # the asking anchor's feature
    assert report.source_index.tolist() == [0, 1, 2, *range(4, count), 0]
    # every per-anchor tensor, statistic and Adam moment follows the new anchor set
    optimizer = trainer.optimizer
    assert optimizer.param("scaffold_features") is strategy.features
    assert optimizer.param("means") is trainer.gaussians.params["means"]
    assert optimizer.adam.state[strategy.features]["exp_avg"].shape == strategy.features.shape
    assert strategy.gradient_accum.shape == (count * 2,) and strategy.anchor_visits.shape == (count,)
    assert float(strategy.anchor_visits.sum()) == 0.0  # judged anchors start again
    trainer.train_step(2)  # and training goes on with them


class _Losses(TrainHook):
    name = "losses"

    def __init__(self):
        self.values = []

    def after_backward(self, run, context):
        self.values.append(float(context.loss.detach()))


def test_a_short_seeded_run_lowers_its_loss_and_writes_a_loadable_ply(scene, tmp_path):
    from esgs.core.formats.ply import read_gaussians_ply
    from esgs.core.train.evaluate import load_run_model

    losses = _Losses()
    result = train(_config(scene, tmp_path / "run"), hooks=[losses])
    assert result.status == "completed"
    assert np.mean(losses.values[-10:]) < 0.6 * np.mean(losses.values[:10])
    ply = read_gaussians_ply(result.point_cloud)
    model = load_run_model(tmp_path / "run")
    assert len(ply) == len(model) == result.metrics["n_gaussians"] > result.n_gaussians  # decoded > anchors
    assert np.isfinite(ply.means).all() and (ply.opacities() > 0).all()
    assert result.metrics["psnr"] > 15 and len(result.metrics["views"]) == 2
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["method"] == "scaffold-gs" and saved["method_config"]["scaffold_offsets"] == 10
    # the end-of-run evaluation decodes each held-out view for its own camera
    state = load_checkpoint(latest_checkpoint(tmp_path / "run" / "checkpoints"))
    assert {"features", "offsets", "log_scaling", "voxel_size"} <= set(state["densify"])
    assert "opacity.0.weight" in state["hooks"]["scaffold_gs"]["decoder"]


def test_the_evaluation_uses_per_view_decoding(scene, tmp_path):
    config = _config(scene, tmp_path / "run", iterations=20)
    trainer = make_trainer(config)
    trainer.run()
    hook = next(h for h in trainer.hooks if isinstance(h, ScaffoldHook))
    view = trainer.data.test[0]
    per_view = hook.view_params(trainer, view, None)
    reference = hook.model_params(trainer, None)
    assert not torch.equal(per_view.opacities[:10], reference.opacities[:10]) or \
        per_view.means.shape != reference.means.shape
    with torch.no_grad():
        rendered = trainer.render(per_view, view).image.clamp(0, 1)
    from esgs.core.metrics.image import psnr

    expected = float(psnr(rendered.permute(2, 0, 1)[None], view.image_float().permute(2, 0, 1)[None]))
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["views"][0]["psnr"] == pytest.approx(expected, abs=1e-4)


def test_resume_continues_the_run_as_if_uninterrupted(scene, tmp_path):
    full = train(_config(scene, tmp_path / "full", iterations=40, evaluate=False))
    first = _config(scene, tmp_path / "split", iterations=40, evaluate=False, checkpoint_every=20)
    trainer = make_trainer(first)
    trainer._start_run_dir(None)
    trainer.setup()
    for step in range(1, 21):
        trainer.train_step(step)
    trainer.save_checkpoint()
    resumed = train(_config(scene, tmp_path / "split", iterations=40, evaluate=False, checkpoint_every=20,
                            resume=True))
    assert resumed.step == 40 and resumed.n_gaussians == full.n_gaussians
    a = load_checkpoint(list_checkpoints(tmp_path / "full" / "checkpoints")[-1][1])
    b = load_checkpoint(list_checkpoints(tmp_path / "split" / "checkpoints")[-1][1])
    for name in ("features", "offsets", "log_scaling", "gradient_accum", "opacity_accum"):
        assert torch.equal(a["densify"][name], b["densify"][name]), name  # bitwise on the CPU
    for name, value in a["hooks"]["scaffold_gs"]["decoder"].items():
        assert torch.equal(value, b["hooks"]["scaffold_gs"]["decoder"][name]), name
    assert torch.equal(a["gaussians"]["params"]["means"], b["gaussians"]["params"]["means"])


def test_settings_are_checked_and_reach_the_command_line(tmp_path):
    import argparse

    from esgs.core.commands import train as train_command

    with pytest.raises(ConfigError, match="scaffold_offsets"):
        get_method("scaffold-gs").build(ScaffoldGSConfig(scaffold_offsets=0), TrainConfig())
    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    args = parser.parse_args(["scene", "--out", str(tmp_path / "run"), "--method", "scaffold-gs",
                              "--scaffold-offsets", "5", "--scaffold-voxel-size", "0.2"])
    config = train_command.build_config(args)
    assert config.method == "scaffold-gs"
    assert config.method_config == ScaffoldGSConfig(scaffold_offsets=5, scaffold_voxel_size=0.2)
    assert get_method("scaffold-gs").label == "Scaffold-GS"
