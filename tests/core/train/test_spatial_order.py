"""Morton order of the Gaussians: the codes, the permutation of every per-Gaussian state, the trainer."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from esgs.core.errors import ConfigError
from esgs.core.train import train
from esgs.core.train.checkpoint import list_checkpoints, load_checkpoint
from esgs.core.train.densify import DensifyState
from esgs.core.train.gaussians import GaussianModel
from esgs.core.train.optim import TrainOptimizer
from esgs.core.train.spatial_order import (is_spatially_ordered, morton_codes, reorder_gaussians, sort_gaussians,
                                           spatial_order)
from esgs.core.train.trainer import Trainer

from .conftest import train_then_checkpoint


def _reference_morton(cell: tuple[int, int, int], bits: int) -> int:
    """Bit-by-bit interleave (x in bit 0, y in bit 1, z in bit 2), the definition the fast code implements."""
    code = 0
    for bit in range(bits):
        for axis in range(3):
            code |= ((cell[axis] >> bit) & 1) << (3 * bit + axis)
    return code


def test_morton_codes_match_the_bitwise_definition():
    rng = np.random.default_rng(0)
    bits = 21
    cells = rng.integers(0, 1 << bits, size=(200, 3))
    cells[0] = (0, 0, 0)
    cells[1] = ((1 << bits) - 1,) * 3  # the upper corner pins the bounding box: cell = coordinate
    codes = morton_codes(torch.tensor(cells, dtype=torch.float64), bits)
    assert codes.dtype == torch.int64 and int(codes.min()) >= 0
    assert codes.tolist() == [_reference_morton(tuple(int(v) for v in c), bits) for c in cells]


def test_morton_sort_puts_the_points_of_each_octant_together():
    # the eight corners of a cube, each with a tight cluster of 5 points, shuffled
    rng = np.random.default_rng(1)
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float64)
    points = np.repeat(corners, 5, axis=0) * 10.0 + rng.uniform(0, 0.5, (40, 3))
    labels = np.repeat(np.arange(8), 5)
    shuffle = rng.permutation(40)
    points, labels = points[shuffle], labels[shuffle]
    order = spatial_order(torch.tensor(points)).numpy()
    sorted_labels = labels[order]
    # each cluster is one contiguous run, and the runs come in Z order: x fastest, then y, then z
    assert sorted_labels.tolist() == [corner for corner in range(8) for _ in range(5)]
    assert sorted(order.tolist()) == list(range(40))


def test_morton_order_keeps_neighbours_close_in_memory():
    # a 64 x 64 grid of points on a plane: consecutive points after the sort are near neighbours
    u = np.arange(64, dtype=np.float64)
    x, y = np.meshgrid(u, u, indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    shuffled = points[np.random.default_rng(2).permutation(len(points))]
    order = spatial_order(torch.tensor(shuffled)).numpy()
    steps = np.linalg.norm(np.diff(shuffled[order], axis=0), axis=1)
    random_steps = np.linalg.norm(np.diff(shuffled, axis=0), axis=1)
    assert np.median(steps) == 1.0  # Z-curve: most consecutive points are grid neighbours
    assert steps.mean() < 0.1 * random_steps.mean()


def test_order_is_deterministic_stable_and_handles_degenerate_input():
    points = torch.randn(500, 3, generator=torch.Generator().manual_seed(3))
    assert torch.equal(spatial_order(points), spatial_order(points.clone()))
    same = torch.ones(7, 3)  # one cell: the stable sort keeps the given order
    assert spatial_order(same).tolist() == list(range(7))
    broken = points[:10].clone()
    broken[4, 1] = float("nan")
    assert sorted(spatial_order(broken).tolist()) == list(range(10))
    assert spatial_order(torch.zeros(0, 3)).numel() == 0
    with pytest.raises(ValueError):
        morton_codes(torch.zeros(4, 2))


def _model(count: int = 300, seed: int = 0) -> GaussianModel:
    generator = torch.Generator().manual_seed(seed)
    means = torch.rand(count, 3, generator=generator) * torch.tensor([2.0, 2.0, 0.2]) + torch.tensor([-1.0, -1.0, 2.0])
    return GaussianModel.from_tensors(
        means=means, sh_dc=torch.randn(count, 1, 3, generator=generator) * 0.5,
        sh_rest=torch.randn(count, 3, 3, generator=generator) * 0.05,
        opacity_logit=torch.randn(count, generator=generator),
        log_scales=torch.log(0.02 + 0.03 * torch.rand(count, 3, generator=generator)),
        quats=torch.randn(count, 4, generator=generator), max_sh_degree=1)


def _optimizer(model: GaussianModel) -> TrainOptimizer:
    optimizer = TrainOptimizer()
    for index, name in enumerate(("means", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats")):
        optimizer.add_group(name, model.params[name], 1e-2 * (index + 1), per_gaussian=True)
    module = torch.nn.Parameter(torch.ones(3))
    optimizer.add_group("module", [module], 1e-2)
    return optimizer


def _per_gaussian_loss(model: GaussianModel) -> torch.Tensor:
    """A sum of per-Gaussian terms: each row's gradient depends on its own row only."""
    p = model.params
    return ((p["means"] - 0.3).pow(2).sum() + torch.sin(p["sh_dc"]).sum() + p["sh_rest"].pow(3).sum()
            + torch.sigmoid(p["opacity_logit"]).sum() + p["log_scales"].exp().sum() + p["quats"].pow(2).sum())


def _adam_state(optimizer: TrainOptimizer, model: GaussianModel, name: str, key: str) -> torch.Tensor:
    return optimizer.adam.state[model.params[name]][key]


def test_one_step_after_reordering_equals_the_permuted_step():
    # two identical models with non-zero Adam moments (three steps)
    models = [_model(), _model()]
    optimizers = [_optimizer(m) for m in models]
    for model, optimizer in zip(models, optimizers):
        for _ in range(3):
            _per_gaussian_loss(model).backward()
            optimizer.step()
            optimizer.zero_grad()
    states = [DensifyState.zeros(len(m)) for m in models]
    for state in states:
        state.grad_accum = torch.arange(len(models[0]), dtype=torch.float32)
        state.visible_count = torch.arange(len(models[0]), dtype=torch.float32) % 5
        state.max_radii = torch.arange(len(models[0]), dtype=torch.float32) * 0.5
    order = spatial_order(models[0].params["means"])
    assert not torch.equal(order, torch.arange(len(order)))

    # A: reorder, then step.  B: step, then permute the result
    reorder_gaussians(models[0], order, optimizers[0], states[0])
    assert is_spatially_ordered(models[0].params["means"])
    assert sort_gaussians(models[0], optimizers[0], states[0]) is None  # already sorted: nothing to do
    for model, optimizer in zip(models, optimizers):
        _per_gaussian_loss(model).backward()
        optimizer.step()
        optimizer.zero_grad()
    # the same arithmetic per element; vectorised kernels (fused Adam, exp, sin) round elements
    # in their vector body and their scalar tail differently, and the permutation moves elements
    # between the two: equal to float32 rounding, not bitwise
    for name in models[0].params:
        torch.testing.assert_close(models[0].params[name].detach(), models[1].params[name].detach()[order],
                                   rtol=1e-5, atol=0)
        for key in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(_adam_state(optimizers[0], models[0], name, key),
                                       _adam_state(optimizers[1], models[1], name, key)[order], rtol=1e-5, atol=0)
    module_a, module_b = (o.adam.param_groups[-1]["params"][0] for o in optimizers)
    assert torch.equal(module_a, module_b)  # module groups are not per-Gaussian: untouched
    assert torch.equal(states[0].grad_accum, order.float())
    assert torch.equal(states[0].max_radii, order.float() * 0.5)


def test_reordering_leaves_the_rendered_image_unchanged():
    from esgs.core.train.rendering import render_view

    model = _model(400, seed=5)
    width, height = 48, 36
    viewmat = torch.eye(4)
    K = torch.tensor([[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]])
    before = render_view(model.render_params(1), viewmat, K, width, height, render_depth=True, backend="cpu")
    reorder_gaussians(model, spatial_order(model.params["means"]))
    after = render_view(model.render_params(1), viewmat, K, width, height, render_depth=True, backend="cpu")
    assert before.image.abs().max() > 0.1  # something is in view
    torch.testing.assert_close(after.image, before.image, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(after.depth, before.depth, atol=1e-5, rtol=1e-5)


def test_reorder_rejects_a_wrong_length():
    model = _model(10)
    with pytest.raises(ValueError, match="order"):
        reorder_gaussians(model, torch.arange(9))


# --- the trainer --------------------------------------------------------------------

def _densifying(fast_config, **overrides):
    # densify after every step from step 2 (scaled from 4000 of 30,000) to the end of the run
    # sky none: the checks here are on the Gaussians' order (the last steps move centres a little,
    # and how much depends on what else shares the image)
    values = dict(iterations=16, densify_from=4000, densify_until=30000, min_densify_interval=1,
                  max_gaussians=600, evaluate=False, opacity_reset_every=0, sky="none")
    values.update(overrides)
    return fast_config(**values)


def test_trainer_keeps_the_gaussians_in_morton_order_through_densification(fast_config):
    trainer = Trainer(_densifying(fast_config))
    trainer.setup()
    means = trainer.gaussians.params["means"]
    assert is_spatially_ordered(means)
    assert not is_spatially_ordered(torch.tensor(trainer.data.points_xyz))  # the sort did something
    counts = [len(trainer.gaussians)]
    for step in range(1, 9):
        trainer.train_step(step)
        counts.append(len(trainer.gaussians))
        if trainer.schedule.is_densify_step(step):  # between densifications the Gaussians move freely
            assert is_spatially_ordered(trainer.gaussians.params["means"]), step
        sizes = trainer.optimizer.state_sizes()
        assert all(size[0] == len(trainer.gaussians) for size in sizes.values())
        assert len(trainer.strategy.state.grad_accum) == len(trainer.gaussians)
    assert counts[-1] > counts[0]  # densification still grows the model


def test_source_index_names_each_gaussians_origin_after_the_sort(fast_config):
    from esgs.core.train.hooks import TrainHook

    class Recorder(TrainHook):
        name = "recorder"

        def __init__(self):
            self.reports = []

        def on_densify(self, trainer, report):
            self.reports.append(report)

    recorder = Recorder()
    trainer = Trainer(_densifying(fast_config, densify_grad_threshold=1e-9, percent_dense=0.1), hooks=[recorder])
    trainer.setup()
    for step in (1, 2):  # no densification yet (it starts after step 2): gradients accumulate
        trainer.train_step(step)
    before = {name: p.detach().clone() for name, p in trainer.gaussians.params.items()}
    report = trainer.strategy._densify(3)  # what the default strategy reports to the hooks
    after = trainer.gaussians.params
    assert report.split > 0 and report.cloned > 0 and report.count_after == len(trainer.gaussians)
    assert is_spatially_ordered(after["means"])
    # every Gaussian carries its source's colour, opacity and rotation (clones and split
    # children copy them), wherever the sort put it
    for name in ("sh_dc", "sh_rest", "opacity_logit", "quats"):
        assert torch.equal(after[name].detach(), before[name][report.source_index]), name
    # the survivors and the clones keep their source's centre exactly
    same_centre = (after["means"].detach() == before["means"][report.source_index]).all(dim=1)
    assert int(same_centre.sum()) >= report.count_after - 2 * report.split
    # new rows (clones, children) start with zero moments; the others kept their source's
    moments = trainer.optimizer.adam.state[after["sh_dc"]]["exp_avg"]
    assert int((moments.abs().sum(dim=(1, 2)) > 0).sum()) <= report.count_before


def test_same_seed_same_run_and_switch_off_keeps_the_old_order(fast_config, tmp_path):
    a = train(_densifying(fast_config, out=tmp_path / "a", iterations=10))
    b = train(_densifying(fast_config, out=tmp_path / "b", iterations=10))
    assert a.n_gaussians == b.n_gaussians
    state_a = load_checkpoint(list_checkpoints(tmp_path / "a" / "checkpoints")[-1][1])
    state_b = load_checkpoint(list_checkpoints(tmp_path / "b" / "checkpoints")[-1][1])
    for name, value in state_a["gaussians"]["params"].items():
        assert torch.equal(value, state_b["gaussians"]["params"][name]), name
    assert state_a["config"]["spatial_order"] is True
    assert is_spatially_ordered(state_a["gaussians"]["params"]["means"])

    off = Trainer(_densifying(fast_config, out=tmp_path / "off", spatial_order=False))
    off.setup()
    torch.testing.assert_close(off.gaussians.params["means"].detach(),
                               torch.tensor(off.data.points_xyz, dtype=torch.float32))


def test_resume_across_densification_equals_uninterrupted(fast_config, tmp_path):
    full = train(_densifying(fast_config, out=tmp_path / "full"))
    first = _densifying(fast_config, out=tmp_path / "split", checkpoint_every=8)
    train_then_checkpoint(first, 8)
    resumed = train(_densifying(fast_config, out=tmp_path / "split", checkpoint_every=8, resume=True))
    assert resumed.step == 16 and resumed.n_gaussians == full.n_gaussians
    a = load_checkpoint(list_checkpoints(tmp_path / "full" / "checkpoints")[-1][1])
    b = load_checkpoint(list_checkpoints(tmp_path / "split" / "checkpoints")[-1][1])
    for name, value in a["gaussians"]["params"].items():
        assert torch.equal(value, b["gaussians"]["params"][name]), name  # bitwise on the CPU
    for key in ("grad_accum", "visible_count", "max_radii"):
        assert torch.equal(a["densify"][key], b["densify"][key]), key


def test_a_run_saved_before_the_switch_resumes_in_its_old_order(fast_config, tmp_path):
    import json

    from esgs.core.train.config import load_run_config

    config = _densifying(fast_config, out=tmp_path / "old", iterations=6, checkpoint_every=3, spatial_order=False)
    train(config)
    # an older run's files have no spatial_order setting at all
    path = config.out / "config.json"
    data = json.loads(path.read_text())
    del data["spatial_order"]
    path.write_text(json.dumps(data))
    (_, first), (_, last) = list_checkpoints(config.out / "checkpoints")
    last.unlink()  # resume from step 3
    checkpoint = first
    state = torch.load(checkpoint, weights_only=True)
    del state["config"]["spatial_order"]
    torch.save(state, checkpoint)
    stored = load_run_config(path)
    assert stored.spatial_order is False
    # the command line reads the run's config.json: the older run continues without the sort
    from esgs.core.cli import main

    assert main(["train", str(config.scene), "--out", str(config.out), "--resume", "--quiet", "--no-evaluate"]) == 0
    resumed = load_checkpoint(list_checkpoints(config.out / "checkpoints")[-1][1])
    assert resumed["step"] == 6 and resumed["config"]["spatial_order"] is False
    # the default (on) differs from what the older run did: refused with a message naming it
    with pytest.raises(ConfigError, match="spatial_order False -> True"):
        train(_densifying(fast_config, out=tmp_path / "old", iterations=6, checkpoint_every=3, resume=True))
