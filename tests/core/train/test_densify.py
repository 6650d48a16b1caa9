"""Clone / split / prune on constructed cases; Adam state follows the Gaussians."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from esgs.core.render.projection import quaternion_to_matrix
from esgs.core.train.densify import DensifySettings, DensifyState, densify_and_prune, reset_opacity
from esgs.core.train.gaussians import GaussianModel, PARAMETER_NAMES
from esgs.core.train.optim import TrainOptimizer

EXTENT = 10.0


def _model(log_scales, opacities, quats=None):
    count = len(opacities)
    means = torch.arange(count * 3, dtype=torch.float32).reshape(count, 3)
    quats = torch.tensor([[1.0, 0, 0, 0]] * count) if quats is None else quats
    opacity = torch.tensor(opacities, dtype=torch.float32)
    return GaussianModel.from_tensors(
        means=means, sh_dc=torch.rand(count, 1, 3), sh_rest=torch.rand(count, 15, 3),
        opacity_logit=torch.log(opacity / (1 - opacity)), log_scales=torch.tensor(log_scales, dtype=torch.float32),
        quats=quats, max_sh_degree=3)


def _optimizer(model):
    optimizer = TrainOptimizer()
    for name in PARAMETER_NAMES:
        optimizer.add_group(name, model.params[name], 1e-3, per_gaussian=True)
    # one step so every group has Adam moments, with a recognisable gradient per row
    for name, param in model.params.items():
        param.grad = torch.ones_like(param) * (torch.arange(len(model), dtype=torch.float32) + 1).reshape(
            (-1,) + (1,) * (param.dim() - 1))
    optimizer.step()
    optimizer.zero_grad()
    return optimizer


def _settings(**overrides):
    values = dict(grad_threshold=2e-4, percent_dense=0.01, extent=EXTENT, prune_opacity=0.005, prune_large=False,
                  max_screen_size_px=20.0, max_world_size=0.1, max_gaussians=1000)
    values.update(overrides)
    return DensifySettings(**values)


def _state(grads, radii=None):
    count = len(grads)
    state = DensifyState.zeros(count)
    state.grad_accum = torch.tensor(grads, dtype=torch.float32) * 2  # two visible steps
    state.visible_count = torch.full((count,), 2.0)
    state.max_radii = torch.tensor(radii if radii is not None else [1.0] * count)
    return state


# Gaussian roles: 0 small+high grad (clone), 1 large+high grad (split), 2 small+low grad (keep),
# 3 transparent (prune), 4 large+low grad (keep), 5 never visible (keep)
SMALL, LARGE = math.log(0.05), math.log(0.5)  # percent_dense * extent = 0.1
LOG_SCALES = [[SMALL] * 3, [LARGE, SMALL, SMALL], [SMALL] * 3, [SMALL] * 3, [LARGE] * 3, [SMALL] * 3]
OPACITIES = [0.5, 0.5, 0.5, 0.001, 0.5, 0.5]
GRADS = [1e-3, 1e-3, 1e-5, 1e-5, 1e-5, 0.0]


def test_clone_split_prune_counts_and_state_sizes():
    model = _model(LOG_SCALES, OPACITIES)
    optimizer = _optimizer(model)
    before = {name: p.detach().clone() for name, p in model.params.items()}
    moments = {name: optimizer.adam.state[p]["exp_avg"].clone() for name, p in model.params.items()}
    state = _state(GRADS)
    report = densify_and_prune(model, optimizer, state, _settings(), step=600,
                               generator=torch.Generator().manual_seed(0))
    assert (report.cloned, report.split, report.pruned) == (1, 1, 1)
    # 6 + 1 clone + 2 children - 1 split parent - 1 transparent = 7
    assert len(model) == report.count_after == 7
    assert report.source_index.tolist() == [0, 2, 4, 5, 0, 1, 1]
    for name, param in model.params.items():
        assert optimizer.param(name) is param
        assert optimizer.state_sizes()[name] == tuple(param.shape)
        adam_state = optimizer.adam.state[param]
        # kept rows keep their moments; new rows (clone, children) start at zero
        assert torch.equal(adam_state["exp_avg"][:4], moments[name][[0, 2, 4, 5]])
        assert not adam_state["exp_avg"][4:].any()
        assert torch.equal(param.detach()[4], before[name][0])  # the clone copies its source
    # split children: scale / 1.6, same colour/rotation/opacity as the parent, positions near it
    children = model.params["log_scales"].detach()[5:]
    assert torch.allclose(children, before["log_scales"][1].expand(2, 3) - math.log(1.6))
    assert torch.equal(model.params["sh_rest"].detach()[5], before["sh_rest"][1])
    offsets = model.params["means"].detach()[5:] - before["means"][1]
    assert (offsets.abs() < 4 * torch.tensor([0.5, 0.05, 0.05])).all() and offsets.abs().sum() > 0
    # statistics restart after a densification
    assert state.grad_accum.shape == (7,) and not state.grad_accum.any() and not state.visible_count.any()


def test_split_samples_follow_the_rotated_parent():
    # one elongated Gaussian rotated 90 degrees about z: its long axis is world y
    half = math.sqrt(0.5)
    model = _model([[math.log(2.0), math.log(0.2), math.log(0.2)]], [0.5],
                   quats=torch.tensor([[half, 0.0, 0.0, half]]))
    _optimizer(model)
    offsets = []
    generator = torch.Generator().manual_seed(1)
    for _ in range(200):
        trial = _model([[math.log(2.0), math.log(0.2), math.log(0.2)]], [0.5], quats=torch.tensor([[half, 0, 0, half]]))
        densify_and_prune(trial, _optimizer(trial), _state([1.0]), _settings(), step=1, generator=generator)
        offsets.append(trial.params["means"].detach() - model.params["means"].detach())
    spread = torch.cat(offsets).std(dim=0)
    assert spread[1] == pytest.approx(2.0, rel=0.15) and spread[0] == pytest.approx(0.2, rel=0.15)


def test_large_pruning_after_reset():
    model = _model([[SMALL] * 3, [math.log(1.5)] * 3, [SMALL] * 3], [0.5, 0.5, 0.5])
    optimizer = _optimizer(model)
    state = _state([0.0, 0.0, 0.0], radii=[5.0, 5.0, 30.0])
    report = densify_and_prune(model, optimizer, state, _settings(prune_large=True), step=4000,
                               generator=torch.Generator())
    # world size 1.5 > 0.1 * extent; screen radius 30 > 20 px
    assert report.pruned == 2 and len(model) == 1 and report.source_index.tolist() == [0]
    model = _model([[SMALL] * 3, [math.log(1.5)] * 3, [SMALL] * 3], [0.5, 0.5, 0.5])
    report = densify_and_prune(model, _optimizer(model), _state([0.0] * 3, radii=[5.0, 5.0, 30.0]), _settings(),
                               step=400, generator=torch.Generator())
    assert report.pruned == 0 and len(model) == 3


def test_cap_limits_growth_to_highest_gradients_and_warns_once():
    count = 10
    model = _model([[SMALL] * 3] * count, [0.5] * count)
    optimizer = _optimizer(model)
    grads = [1e-3 * (i + 1) for i in range(count)]
    state = _state(grads)
    with pytest.warns(RuntimeWarning, match="max_gaussians"):
        report = densify_and_prune(model, optimizer, state, _settings(max_gaussians=13), step=600,
                                   generator=torch.Generator())
    assert report.capped and len(model) == 13
    assert report.source_index[count:].tolist() == [7, 8, 9]  # the three largest gradients
    state = _state(grads + [1e-3] * 3)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        state.warned_cap = True
        report = densify_and_prune(model, optimizer, state, _settings(max_gaussians=13), step=700,
                                   generator=torch.Generator())
    assert len(model) == 13


def test_accumulate_converts_pixel_gradients_to_ndc():
    """The statistic equals the gradient norm w.r.t. NDC centres, computed through autograd."""
    width, height = 64, 48
    ndc = torch.tensor([[0.1, -0.2], [0.5, 0.5], [-0.3, 0.7]], requires_grad=True)
    pixels = torch.stack([((ndc[:, 0] + 1) * width - 1) * 0.5, ((ndc[:, 1] + 1) * height - 1) * 0.5], dim=-1)
    pixels.retain_grad()
    weights = torch.tensor([[1.0, 2.0], [-3.0, 0.5], [0.7, 0.7]])
    (pixels * weights * 1e-4).sum().backward()
    state = DensifyState.zeros(3)
    radii = torch.tensor([[3, 0, 2]])
    state.accumulate(pixels.grad[None], radii, width, height)
    state.accumulate(pixels.grad[None], radii, width, height)
    expected = ndc.grad.norm(dim=-1)
    assert torch.allclose(state.mean_gradients(), expected * torch.tensor([1.0, 0.0, 1.0]))
    assert state.visible_count.tolist() == [2, 0, 2] and state.max_radii.tolist() == [3, 0, 2]


def test_reset_opacity_clamps_and_zeroes_moments():
    model = _model([[SMALL] * 3] * 3, [0.9, 0.005, 0.5])
    optimizer = _optimizer(model)
    reset_opacity(model, optimizer, 0.01)
    assert torch.allclose(model.opacities(), torch.tensor([0.01, 0.005, 0.01]), atol=1e-4)
    assert optimizer.param("opacity_logit") is model.params["opacity_logit"]
    assert not optimizer.adam.state[model.params["opacity_logit"]]["exp_avg"].any()
    assert optimizer.adam.state[model.params["means"]]["exp_avg"].any()


def test_the_split_rotation_is_orthonormal_and_matches_colmap():
    from esgs.core.colmap.geometry import quat_wxyz_to_matrix

    quats = torch.randn(20, 4, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    rotations = quaternion_to_matrix(quats)  # what densification rotates split offsets with
    for quat, rotation in zip(quats.numpy(), rotations.numpy()):
        assert np.allclose(rotation, quat_wxyz_to_matrix(quat))
