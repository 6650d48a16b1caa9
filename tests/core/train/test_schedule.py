"""Schedules scale with ``iterations``; learning rates follow 3DGS's exponential decay."""
from __future__ import annotations

import math

import pytest

from esgs.core.errors import ConfigError
from esgs.core.train.config import TrainConfig
from esgs.core.train.optim import ExponentialDecay


def test_paper_schedule_is_unscaled_at_30000_steps():
    schedule = TrainConfig().schedule()
    assert (schedule.densify_from, schedule.densify_until, schedule.densify_every) == (500, 15000, 100)
    assert (schedule.opacity_reset_every, schedule.sh_increase_every) == (3000, 1000)
    assert schedule.is_densify_step(600) and not schedule.is_densify_step(500) and not schedule.is_densify_step(15000)
    assert schedule.is_opacity_reset_step(3000) and not schedule.is_opacity_reset_step(18000)
    assert [schedule.sh_degree_at(s, 3) for s in (1, 1000, 1001, 2001, 3001, 29000)] == [0, 0, 1, 2, 3, 3]
    assert not schedule.prunes_large(3000) and schedule.prunes_large(3001)


@pytest.mark.parametrize("iterations", [12000, 60000])
def test_schedule_scales_in_proportion(iterations):
    config = TrainConfig(iterations=iterations)
    schedule = config.schedule()
    factor = iterations / 30000
    assert schedule.densify_from == round(500 * factor)
    assert schedule.densify_until == round(15000 * factor)
    assert schedule.densify_every == max(1, round(100 * factor))
    assert schedule.opacity_reset_every == round(3000 * factor)
    # densification happens, and stops at half the run as in the paper
    densify_steps = [s for s in range(1, iterations + 1) if schedule.is_densify_step(s)]
    assert densify_steps and densify_steps[-1] < iterations / 2 <= densify_steps[-1] + schedule.densify_every
    assert densify_steps[0] > schedule.densify_from
    # about as many densifications as the paper's run (144), up to rounding of the interval
    assert abs(len(densify_steps) - 144) <= 0.06 * 144
    assert schedule.sh_degree_at(iterations, 3) == 3


@pytest.mark.parametrize("iterations", [300, 2000])
def test_short_runs_keep_minimum_intervals(iterations):
    """Windows scale with the run, but densification and resets keep sane minimum intervals."""
    config = TrainConfig(iterations=iterations)
    schedule = config.schedule()
    factor = iterations / 30000
    assert schedule.densify_from == round(500 * factor)
    assert schedule.densify_until == round(15000 * factor)
    assert schedule.densify_every == config.min_densify_interval == 20
    assert schedule.opacity_reset_every == config.min_opacity_reset_interval == 1000
    densify_steps = [s for s in range(1, iterations + 1) if schedule.is_densify_step(s)]
    assert densify_steps and densify_steps[-1] < iterations / 2
    assert all(b - a == 20 for a, b in zip(densify_steps, densify_steps[1:]))
    resets = [s for s in range(1, iterations + 1) if schedule.is_opacity_reset_step(s)]
    assert resets == [s for s in (1000,) if s < iterations / 2]
    assert schedule.sh_degree_at(iterations, 3) == 3


def test_no_densify_disables_densification_and_resets():
    schedule = TrainConfig(iterations=2000, densify=False).schedule()
    assert not any(schedule.is_densify_step(s) or schedule.is_opacity_reset_step(s) for s in range(1, 2001))


@pytest.mark.parametrize("iterations", [2000, 30000])
def test_position_lr_decays_over_the_whole_run(iterations):
    decay = ExponentialDecay(1.6e-4 * 2.0, 1.6e-6 * 2.0, max_steps=iterations)
    assert decay(0) == pytest.approx(3.2e-4)
    assert decay(iterations) == pytest.approx(3.2e-6)
    # log-linear: at a quarter and half of the run the rate is 10^-0.5 and 10^-1 of the start
    assert decay(iterations // 2) == pytest.approx(3.2e-4 * 10 ** -1.0, rel=1e-6)
    assert decay(iterations // 4) == pytest.approx(3.2e-4 * 10 ** -0.5, rel=1e-6)
    assert decay(2 * iterations) == pytest.approx(3.2e-6)  # clipped after the end


def test_delay_warm_up():
    decay = ExponentialDecay(1.0, 1.0, max_steps=100, delay_steps=10, delay_mult=0.01)
    assert decay(0) == pytest.approx(0.01)
    assert decay(5) == pytest.approx(0.01 + 0.99 * math.sin(math.pi / 4))
    assert decay(10) == pytest.approx(1.0)


def test_trainer_lr_schedule_at_fractions(fast_config):
    from esgs.core.train.trainer import Trainer

    trainer = Trainer(fast_config(iterations=200))
    trainer.setup()
    extent = trainer.data.extent
    rates = {}
    for step in (1, 100, 200):
        trainer.optimizer.update_learning_rates(step)
        rates[step] = trainer.optimizer.learning_rate("means")
    assert rates[1] == pytest.approx(1.6e-4 * extent * 10 ** (-2 / 200), rel=1e-6)
    assert rates[100] == pytest.approx(1.6e-5 * extent, rel=1e-6)
    assert rates[200] == pytest.approx(1.6e-6 * extent, rel=1e-6)
    assert trainer.optimizer.learning_rate("sh_rest") == pytest.approx(2.5e-3 / 20)
    assert trainer.optimizer.learning_rate("opacity_logit") == pytest.approx(0.05)


@pytest.mark.parametrize("bad", [dict(iterations=0), dict(backend="gpu"), dict(sh_degree=4), dict(test_every=1),
                                 dict(init_opacity=1.0), dict(background=(0.0, 0.0))])
def test_validate_rejects_bad_settings(bad):
    with pytest.raises(ConfigError):
        TrainConfig(**bad).validate()
