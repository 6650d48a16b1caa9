"""The clone/split statistic of ``densify_gradient = "photometric"`` (an option; the default is "all"): prior-like terms (LossTerm
with ``densifies=False``) move the Gaussians but leave the statistic as the images alone make it."""
from __future__ import annotations

import pytest
import torch

from esgs.core.errors import ConfigError
from esgs.core.train import TrainConfig
from esgs.core.train.hooks import TrainHook
from esgs.core.train.losses import LossContext, LossTerm, loss_parts


class _Recorder(TrainHook):
    """Adds a depth term that pulls every pixel's depth towards 0 (a stand-in prior loss) and
    records step 1's screen-space gradients, the kept densifying share and the parameters' gradients."""

    name = "recorder"

    def __init__(self, weight: float, densifies: bool = False):
        self.weight, self.densifies = weight, densifies
        self.record: dict = {}

    def setup(self, trainer):
        if self.weight:
            trainer.add_loss_term(LossTerm("pull", self.weight, lambda ctx: ctx.depth.mean(),
                                           needs=frozenset({"depth"}), densifies=self.densifies))

    def after_backward(self, trainer, context):
        if context.step != 1:
            return
        meta = context.output.meta
        self.record = {"total": meta["means2d"].grad.detach().clone(),
                       "kept": meta.get("densify_grad"),
                       "params": {k: p.grad.detach().clone() for k, p in trainer.gaussians.params.items()},
                       "accumulating": trainer.strategy.gathers_statistics(1)}


def _step_one(fast_config, hook, **overrides):
    from esgs.core.train.trainer import Trainer

    overrides.setdefault("densify_gradient", "photometric")
    config = fast_config(iterations=30, evaluate=False, **overrides)
    config.out = config.out.with_name(f"run_{hook.weight}_{hook.densifies}_{config.densify_gradient}")
    trainer = Trainer(config, hooks=[hook])
    trainer._start_run_dir(None)
    trainer.setup()
    trainer.train_step(1)
    return trainer


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_statistic_is_the_photometric_gradient_and_parameters_get_the_full_one(fast_config, backend):
    photometric = _Recorder(weight=0.0)
    _step_one(fast_config, photometric, backend=backend)
    split = _Recorder(weight=5.0)
    split_trainer = _step_one(fast_config, split, backend=backend)
    one_pass = _Recorder(weight=5.0)
    _step_one(fast_config, one_pass, backend=backend, densify_gradient="all")

    assert split.record["accumulating"]
    kept, total = split.record["kept"], split.record["total"]
    # the prior-like term changes the screen-space gradient ...
    assert (total - photometric.record["total"]).abs().max() > 1e-6
    # ... but the statistic is what the photometric terms alone give
    torch.testing.assert_close(kept, photometric.record["total"], rtol=1e-5, atol=1e-9)
    assert one_pass.record["kept"] is None  # "all": one pass, the statistic reads means2d.grad
    # two passes give every parameter the same gradient as one, to float32 rounding of sums whose
    # order differs: an element near zero may keep an error of the order of the largest terms
    for name, grad in one_pass.record["params"].items():
        torch.testing.assert_close(split.record["params"][name], grad, rtol=1e-5,
                                   atol=max(1e-8, 1e-6 * float(grad.abs().max())))
    # and the strategy accumulated the photometric share
    state = split_trainer.strategy.state
    width, height = split_trainer.data.train[0].width, split_trainer.data.train[0].height
    scale = torch.tensor([0.5 * width, 0.5 * height], dtype=kept.dtype)
    expected = ((kept * scale).norm(dim=-1) * (split_trainer.strategy.state.visible_count > 0)).sum(0)
    torch.testing.assert_close(state.grad_accum, expected.to(state.grad_accum.dtype), rtol=1e-5, atol=1e-9)


def test_densifying_terms_take_the_single_pass(fast_config):
    hook = _Recorder(weight=5.0, densifies=True)
    _step_one(fast_config, hook)
    assert hook.record["kept"] is None


def test_loss_parts_groups_terms_by_densifies():
    image = torch.full((2, 2, 3), 0.5, requires_grad=True)
    context = LossContext(step=3, image=image, target=torch.zeros(2, 2, 3), mask=None, alpha=torch.ones(2, 2, 1))
    terms = [LossTerm("a", 2.0, lambda c: c.image.mean()), LossTerm("b", 3.0, lambda c: c.image.sum(), densifies=False),
             LossTerm("late", 1.0, lambda c: c.image.sum(), start_step=10, densifies=False)]
    parts = loss_parts(terms, context)
    assert float(parts.densifying.detach()) == pytest.approx(1.0)
    assert float(parts.other.detach()) == pytest.approx(18.0)
    assert float(parts.total.detach()) == pytest.approx(19.0)
    assert parts.values == {"a": 0.5, "b": 6.0}
    only_prior = loss_parts(terms[1:2], context)
    assert only_prior.densifying is None and float(only_prior.total.detach()) == pytest.approx(18.0)


def test_unknown_densify_gradient_is_refused(tiny_scene, tmp_path):
    with pytest.raises(ConfigError, match="densify_gradient must be one of photometric, all"):
        TrainConfig(scene=tiny_scene, out=tmp_path / "r", densify_gradient="prior").validate()


def test_default_statistic_takes_every_term(fast_config):
    from esgs.core.train.trainer import Trainer

    assert TrainConfig().densify_gradient == "all"
    hook = _Recorder(weight=5.0)
    config = fast_config(iterations=30, evaluate=False)
    trainer = Trainer(config, hooks=[hook])
    trainer._start_run_dir(None)
    trainer.setup()
    trainer.train_step(1)
    assert hook.record["kept"] is None  # one pass: means2d.grad, prior terms included
