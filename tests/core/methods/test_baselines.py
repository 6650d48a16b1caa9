"""Mip-Splatting's 3D filter and DropoutGS's dropout as trainer hooks, on hand-built cases and tiny runs."""
from __future__ import annotations

import json
import math

import pytest
import torch

from esgs.core.methods import DropoutGSConfig, MipSplattingConfig, get_method, make_trainer, train
from esgs.core.methods.baselines.dropout_gs import DropoutHook, apply_dropout, dropout_keep_mask
from esgs.core.methods.baselines.mip_splatting import (MipSplattingHook, apply_3d_filter, filter_variance,
                                               max_sampling_rate)
from esgs.core.errors import ConfigError
from esgs.core.train.config import TrainConfig
from esgs.core.train.gaussians import RenderParams
from esgs.core.train.hooks import StepContext, TrainHook
from tests.core.train.scene import make_scene


def _camera(z_offset: float, focal: float, width: int = 40, height: int = 30):
    """A camera at (0, 0, -z_offset) looking along +z (identity rotation)."""
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[2, 3] = z_offset
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal * 0.8, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return viewmat, K


def test_sampling_rate_is_the_largest_focal_over_depth_among_cameras_that_see_the_centre():
    near_cam = _camera(1.0, 50.0)      # point at z=1 -> depth 2, rate 25
    far_cam = _camera(3.0, 120.0)      # depth 4, rate 30 (largest)
    viewmats = torch.stack([near_cam[0], far_cam[0]])
    Ks = torch.stack([near_cam[1], far_cam[1]])
    means = torch.tensor([[0.0, 0.0, 1.0],      # seen by both: max(50/2, 120/4) = 30
                          [1.4, 0.0, 1.0],      # near cam: u = 20 + 50*1.4/2 = 55 > 40*1.15=46 (not seen); far: 20+120*1.4/4=62 no
                          [0.5, 0.0, 1.0],      # near: u = 32.5 (seen, 25); far: 35 (seen, 30)
                          [0.9, 0.0, 1.0],      # near: u = 42.5 <= 46 (margin, seen, 25); far: 47 > 46 (not seen)
                          [0.0, 0.0, -2.0]],    # behind the near camera (z=-1), in front of far (z=1): 120/1
                         dtype=torch.float64)
    rate, seen = max_sampling_rate(means, viewmats, Ks, [40, 40], [30, 30], margin=0.15)
    assert seen.tolist() == [True, False, True, True, True]
    expected_seen = torch.tensor([30.0, 30.0, 25.0, 120.0], dtype=torch.float64)
    torch.testing.assert_close(rate[seen], expected_seen)
    # unseen centres get the smallest seen rate (widest filter)
    assert float(rate[1]) == pytest.approx(25.0)


def test_3d_filter_matches_the_convolution_formula():
    scales = torch.tensor([[0.1, 0.2, 0.05], [1.0, 1.0, 1.0]], dtype=torch.float64, requires_grad=True)
    opacities = torch.tensor([0.8, 0.5], dtype=torch.float64, requires_grad=True)
    rate = torch.tensor([10.0, 2.0], dtype=torch.float64)
    variance = filter_variance(rate, 0.2)
    torch.testing.assert_close(variance, torch.tensor([0.2 / 100.0, 0.2 / 4.0], dtype=torch.float64))
    new_scales, new_opacities = apply_3d_filter(scales, opacities, variance)
    # covariance route: R diag(s^2) R^T + v I for a random rotation, det ratio and eigenvalues
    for i in range(2):
        rotation, _ = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(i)))
        sigma = rotation @ torch.diag(scales[i].detach() ** 2) @ rotation.T
        filtered = sigma + variance[i] * torch.eye(3, dtype=torch.float64)
        eigen = torch.linalg.eigvalsh(filtered)
        torch.testing.assert_close(torch.sort(new_scales[i].detach() ** 2).values, eigen)
        factor = math.sqrt(float(torch.linalg.det(sigma) / torch.linalg.det(filtered)))
        assert float(new_opacities[i].detach()) == pytest.approx(float(opacities[i].detach()) * factor, rel=1e-10)
    (new_scales.sum() + new_opacities.sum()).backward()
    assert torch.isfinite(scales.grad).all() and (opacities.grad > 0).all()


def test_dropout_drops_the_requested_fraction_deterministically():
    keep = dropout_keep_mask(1000, 0.15, seed=3, step=7)
    assert int((~keep).sum()) == 150
    assert torch.equal(keep, dropout_keep_mask(1000, 0.15, seed=3, step=7))
    assert not torch.equal(keep, dropout_keep_mask(1000, 0.15, seed=3, step=8))
    assert not torch.equal(keep, dropout_keep_mask(1000, 0.15, seed=4, step=7))
    assert bool(dropout_keep_mask(10, 0.0, seed=0, step=1).all())
    params = RenderParams(means=torch.zeros(1000, 3), quats=torch.zeros(1000, 4), scales=torch.ones(1000, 3),
                          opacities=torch.full((1000,), 0.6, requires_grad=True), colors=torch.zeros(1000, 1, 3),
                          sh_degree=0)
    dropped = apply_dropout(params, keep)
    assert torch.equal(dropped.opacities == 0, ~keep)
    assert torch.allclose(dropped.opacities[keep], torch.tensor(0.6))
    compensated = apply_dropout(params, keep, compensate=True, rate=0.15)
    assert torch.allclose(compensated.opacities[keep], torch.tensor(0.6 / 0.85))
    dropped.opacities.sum().backward()
    assert torch.equal(params.opacities.grad, keep.float())


def test_bad_settings_raise_config_errors():
    with pytest.raises(ConfigError, match="dropout_rate"):
        get_method("dropout-gs").build(DropoutGSConfig(dropout_rate=1.0), TrainConfig())
    with pytest.raises(ConfigError):
        TrainConfig(method="mip-splatting", method_config=MipSplattingConfig(mip_filter_3d=-1.0)).validate()
    assert get_method("dropout-gs").build(DropoutGSConfig(dropout_rate=0.0), TrainConfig()).hooks == []


class _Recorder(TrainHook):
    """Records the opacities every training render receives (after the baseline hooks)."""

    name = "recorder"

    def __init__(self):
        self.opacities = []

    def before_render(self, trainer, context, params):
        self.opacities.append(params.opacities.detach().clone())
        return params


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("baselines") / "scene", views=6, width=32, height=24)


def _config(scene, out, method, **settings) -> TrainConfig:
    settings_class = get_method(method).settings_class
    return TrainConfig(scene=scene, out=out, iterations=12, backend="cpu", threads=1, evaluate=True, lpips=False,
                       densify_until=0, test_every=3, save_renders=False, checkpoint_every=0, progress_every=4,
                       method=method, method_config=settings_class(**settings))


def test_dropout_run_drops_in_training_only_and_evaluates_the_full_model(scene, tmp_path):
    recorder = _Recorder()
    result = train(_config(scene, tmp_path / "dropout", "dropout-gs", dropout_rate=0.2), hooks=[recorder])
    assert result.status == "completed" and result.metrics["psnr"] > 0
    for opacities in recorder.opacities:
        assert int((opacities == 0).sum()) == round(0.2 * len(opacities))
    # the same seed drops the same Gaussians; evaluation (and export) leave the model whole
    trainer = make_trainer(_config(scene, tmp_path / "again", "dropout-gs", dropout_rate=0.2))
    trainer.setup()
    hook = next(h for h in trainer.hooks if isinstance(h, DropoutHook))
    assert hook.export_model(trainer, trainer.gaussians) is trainer.gaussians
    config = json.loads((tmp_path / "dropout" / "config.json").read_text())
    assert config["method"] == "dropout-gs" and config["method_config"]["dropout_rate"] == 0.2


def test_mip_splatting_run_filters_renders_and_bakes_the_filter_into_the_ply(scene, tmp_path):
    from esgs.core.formats.ply import read_gaussians_ply

    config = _config(scene, tmp_path / "mip", "mip-splatting")
    trainer = make_trainer(config)
    trainer.setup()
    hook = next(h for h in trainer.hooks if isinstance(h, MipSplattingHook))
    params = trainer.gaussians.render_params(0)
    context = StepContext(step=1, view=trainer.data.train[0], sh_degree=0)
    filtered = hook.before_render(trainer, context, params)
    assert (filtered.scales > params.scales).all() and (filtered.opacities < params.opacities).all()
    assert filtered.scales.requires_grad
    result = train(config)
    assert result.status == "completed" and result.metrics["psnr"] > 0
    from esgs.core.train.checkpoint import latest_checkpoint, load_checkpoint
    from esgs.core.train.gaussians import GaussianModel

    # the PLY holds the checkpoint's raw Gaussians with the filter of their centres folded in
    raw = GaussianModel.from_state_dict(load_checkpoint(latest_checkpoint(tmp_path / "mip" / "checkpoints"))["gaussians"])
    trainer.gaussians = raw
    variance = hook.compute(trainer)
    scales, opacities = apply_3d_filter(torch.exp(raw.params["log_scales"]).detach(),
                                        torch.sigmoid(raw.params["opacity_logit"]).reshape(-1).detach(), variance)
    ply = read_gaussians_ply(result.point_cloud)
    torch.testing.assert_close(torch.from_numpy(ply.log_scales).float(), torch.log(scales), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(torch.sigmoid(torch.from_numpy(ply.opacity_logit).float()), opacities,
                               atol=1e-5, rtol=1e-4)


def test_train_command_flags_reach_the_config(tmp_path):
    import argparse

    from esgs.core.commands import train as train_command

    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    args = parser.parse_args(["scene", "--out", str(tmp_path / "run"), "--dropout-gs", "--dropout-rate", "0.2"])
    config = train_command.build_config(args)
    assert config.method == "dropout-gs" and config.method_config == DropoutGSConfig(dropout_rate=0.2)
    args = parser.parse_args(["scene", "--out", str(tmp_path / "run"), "--method", "mip-splatting",
                              "--mip-filter-2d", "0.2"])
    config = train_command.build_config(args)
    assert config.method == "mip-splatting" and config.method_config == MipSplattingConfig(mip_filter_2d=0.2)
    args = parser.parse_args(["scene", "--out", str(tmp_path / "run")])
    assert train_command.build_config(args).method == "3dgs"
    # one method per run: two switches are refused with a clear error
    args = parser.parse_args(["scene", "--out", str(tmp_path / "run"), "--mip-splatting", "--dropout-gs"])
    with pytest.raises(ConfigError, match="one method per run"):
        train_command.build_config(args)
