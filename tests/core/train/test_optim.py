"""TrainOptimizer: named groups, schedules, row surgery that keeps Adam equivalent."""
from __future__ import annotations

import pytest
import torch

from esgs.core.errors import CheckpointError
from esgs.core.train.optim import TrainOptimizer


def _grad(param, seed):
    return torch.randn(param.shape, generator=torch.Generator().manual_seed(seed))


def test_select_then_step_equals_stepping_the_kept_rows():
    """Pruning rows mid-training gives the same updates as an Adam that only ever saw the kept rows."""
    full = torch.nn.Parameter(torch.randn(6, 3, generator=torch.Generator().manual_seed(0)))
    keep = torch.tensor([True, False, True, True, False, True])
    small = torch.nn.Parameter(full.detach()[keep].clone())
    optimizer, reference = TrainOptimizer(), TrainOptimizer()
    optimizer.add_group("means", full, 0.1, per_gaussian=True)
    reference.add_group("means", small, 0.1, per_gaussian=True)
    for seed in range(3):
        gradient = _grad(full, seed)
        optimizer.param("means").grad = gradient.clone()
        reference.param("means").grad = gradient[keep].clone()
        optimizer.step()
        reference.step()
    new = optimizer.select(keep)
    for seed in range(3, 6):
        gradient = _grad(full, seed)[keep]
        new["means"].grad = gradient.clone()
        reference.param("means").grad = gradient.clone()
        optimizer.step()
        reference.step()
    assert torch.allclose(new["means"], reference.param("means"), atol=1e-6)


def test_append_starts_new_rows_from_zero_moments_and_leaves_module_groups():
    rows = torch.nn.Parameter(torch.zeros(2, 3))
    module = torch.nn.Linear(2, 2)
    optimizer = TrainOptimizer()
    optimizer.add_group("means", rows, 0.1, per_gaussian=True)
    optimizer.add_group("module", module.parameters(), 0.01)
    rows.grad = torch.ones(2, 3)
    for p in module.parameters():
        p.grad = torch.ones_like(p)
    optimizer.step()
    module_state = {k: v.clone() for k, v in optimizer.adam.state[module.weight].items()}
    new = optimizer.append({"means": torch.full((3, 3), 7.0)})["means"]
    assert new.shape == (5, 3) and torch.equal(new.detach()[2:], torch.full((3, 3), 7.0))
    state = optimizer.adam.state[new]
    assert state["exp_avg"].shape == (5, 3) and state["exp_avg"][:2].abs().min() > 0 and not state["exp_avg"][2:].any()
    assert rows not in optimizer.adam.state  # the old tensor's state moved
    assert torch.equal(optimizer.adam.state[module.weight]["exp_avg"], module_state["exp_avg"])
    assert optimizer.per_gaussian_names() == ["means"]


def test_schedules_and_checkpoint_group_check():
    param = torch.nn.Parameter(torch.zeros(1, 3))
    optimizer = TrainOptimizer()
    optimizer.add_group("means", param, 1.0, schedule=lambda step: 1.0 / (step + 1), per_gaussian=True)
    optimizer.update_learning_rates(3)
    assert optimizer.learning_rate("means") == 0.25
    other = TrainOptimizer()
    other.add_group("positions", torch.nn.Parameter(torch.zeros(1, 3)), 1.0, per_gaussian=True)
    with pytest.raises(CheckpointError, match="groups"):
        other.load_state_dict(optimizer.state_dict())
    with pytest.raises(ValueError):
        optimizer.add_group("means", torch.nn.Parameter(torch.zeros(1)), 1.0)


def test_keep_and_append_equals_append_then_select_for_parameters_and_moments():
    """Densification's one-pass surgery: the same parameters and Adam moments as appending the
    new rows and then keeping the rows of the old and new that survive, bit for bit."""
    generator = torch.Generator().manual_seed(5)
    start = {"means": torch.randn(7, 3, generator=generator), "sh_rest": torch.randn(7, 15, 3, generator=generator),
             "opacity_logit": torch.randn(7, generator=generator)}
    extra = {"means": torch.randn(4, 3, generator=generator), "sh_rest": torch.randn(4, 15, 3, generator=generator),
             "opacity_logit": torch.randn(4, generator=generator)}
    keep = torch.tensor([True, False, True, True, False, True, True, False, True, True, False])
    optimizers = []
    for _ in range(2):
        optimizer = TrainOptimizer()
        for name, value in start.items():
            optimizer.add_group(name, torch.nn.Parameter(value.clone()), 0.1, per_gaussian=True)
        for seed in range(3):
            for name in start:
                optimizer.param(name).grad = _grad(optimizer.param(name), seed)
            optimizer.step()
        optimizers.append(optimizer)
    two_pass, one_pass = optimizers
    two_pass.append(extra)
    reference = two_pass.select(keep)
    result = one_pass.keep_and_append(keep[:7], {name: value[keep[7:]] for name, value in extra.items()})
    for name in start:
        assert result[name].shape == reference[name].shape and result[name].is_contiguous()
        assert torch.equal(result[name].detach(), reference[name].detach())
        for moment in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(one_pass.adam.state[result[name]][moment], two_pass.adam.state[reference[name]][moment])
    # and the next step is the same
    for optimizer, params in ((one_pass, result), (two_pass, reference)):
        for name in start:
            params[name].grad = _grad(params[name], 9)
        optimizer.step()
    for name in start:
        assert torch.equal(result[name].detach(), reference[name].detach())
    with pytest.raises(ValueError, match="missing rows for sh_rest"):
        one_pass.keep_and_append(torch.ones(8, dtype=torch.bool), {"means": extra["means"], "opacity_logit": extra["opacity_logit"]})
