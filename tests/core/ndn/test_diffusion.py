"""NDN diffusion: noise schedules, the forward process, predictions and DDIM."""
from __future__ import annotations

import math

import pytest
import torch

from esgs.core.errors import ConfigError
from esgs.core.ndn.config import NDNDiffusionConfig
from esgs.core.ndn.diffusion import GaussianDiffusion, make_betas


@pytest.mark.parametrize("schedule", ["cosine", "linear"])
def test_schedule_is_monotone_and_ends_near_pure_noise(schedule):
    diffusion = GaussianDiffusion(NDNDiffusionConfig(timesteps=1000, schedule=schedule))
    alpha_bar = diffusion.alphas_cumprod
    assert alpha_bar.shape == (1000,)
    assert (alpha_bar[1:] < alpha_bar[:-1]).all()
    assert 0.99 < alpha_bar[0] < 1.0 and 0 < alpha_bar[-1] < 1e-3
    betas = make_betas(1000, schedule)
    torch.testing.assert_close(alpha_bar, torch.cumprod(1 - betas, 0))


def test_q_sample_statistics():
    diffusion = GaussianDiffusion(NDNDiffusionConfig(timesteps=1000))
    generator = torch.Generator().manual_seed(0)
    x0 = torch.full((20000, 1), 0.7)
    for step in (10, 500, 990):
        t = torch.full((20000,), step)
        x_t = diffusion.q_sample(x0, t, torch.randn(x0.shape, generator=generator))
        alpha_bar = float(diffusion.alphas_cumprod[step])
        assert float(x_t.mean()) == pytest.approx(math.sqrt(alpha_bar) * 0.7, abs=0.02)
        assert float(x_t.std()) == pytest.approx(math.sqrt(1 - alpha_bar), abs=0.02)


@pytest.mark.parametrize("prediction", ["epsilon", "v"])
def test_split_prediction_inverts_the_target(prediction):
    diffusion = GaussianDiffusion(NDNDiffusionConfig(timesteps=100, prediction=prediction))
    generator = torch.Generator().manual_seed(1)
    x0 = torch.rand((3, 1, 4, 4), generator=generator) * 2 - 1
    noise = torch.randn(x0.shape, generator=generator)
    t = torch.tensor([0, 50, 99])
    x_t = diffusion.q_sample(x0, t, noise)
    x0_back, noise_back = diffusion.split_prediction(x_t, t, diffusion.target(x0, t, noise))
    torch.testing.assert_close(x0_back, x0, atol=1e-4, rtol=0)
    torch.testing.assert_close(noise_back, noise, atol=1e-4, rtol=0)


@pytest.mark.parametrize("prediction", ["epsilon", "v"])
def test_ddim_with_an_oracle_network_recovers_the_clean_maps(prediction):
    """A network that outputs the exact noise (or v) of known targets: DDIM (eta 0) must land on them."""
    diffusion = GaussianDiffusion(NDNDiffusionConfig(timesteps=1000, sample_steps=10, prediction=prediction))
    generator = torch.Generator().manual_seed(2)
    depth_x0 = torch.rand((2, 1, 6, 8), generator=generator) * 2 - 1
    normal_x0 = torch.nn.functional.normalize(torch.randn((2, 3, 6, 8), generator=generator), dim=1)

    def oracle_output(x_t, t, x0):
        alpha_bar = diffusion.alphas_cumprod[t].float().view(-1, 1, 1, 1)
        noise = (x_t - alpha_bar.sqrt() * x0) / (1 - alpha_bar).sqrt()
        return diffusion.target(x0, t, noise)

    def oracle(views, depth, normal, t):
        return oracle_output(depth, t, depth_x0), oracle_output(normal, t, normal_x0)

    depth, normal = diffusion.sample(oracle, torch.zeros(2, 9, 6, 8), seed=0)
    torch.testing.assert_close(depth, depth_x0, atol=1e-4, rtol=0)
    torch.testing.assert_close(normal, normal_x0, atol=1e-4, rtol=0)
    assert len(diffusion.ddim_timesteps()) == 10 and diffusion.ddim_timesteps()[0] == 999


def test_bad_settings_are_config_errors():
    with pytest.raises(ConfigError, match="schedule"):
        GaussianDiffusion(NDNDiffusionConfig(schedule="quadratic"))
    with pytest.raises(ConfigError, match="sample_steps"):
        GaussianDiffusion(NDNDiffusionConfig(timesteps=10, sample_steps=20))


def test_an_ensemble_combines_the_samples_of_each_view():
    from .conftest import tiny_config
    from esgs.core.ndn.train import build_model

    torch.manual_seed(0)
    model, diffusion = build_model(tiny_config("v"))
    for parameter in model.parameters():
        parameter.data.add_(0.05 * torch.randn_like(parameter))
    model.eval()
    views = torch.rand((2, 9, 18, 32), generator=torch.Generator().manual_seed(3)) * 2 - 1
    single = diffusion.sample(model, views, seed=4)
    for left, right in zip(single, diffusion.sample(model, views, seed=4, ensemble=1)):
        torch.testing.assert_close(left, right, rtol=0, atol=0)  # ensemble 1 is plain sampling
    # the members: each view repeated 3 times in one batch (rows 3b..3b+2 belong to view b)
    members = diffusion.sample(model, views.repeat_interleave(3, dim=0), seed=4)
    depth, normal = diffusion.sample(model, views, seed=4, ensemble=3)
    assert depth.shape == (2, 1, 18, 32) and normal.shape == (2, 3, 18, 32)
    for combined, every in zip((depth, normal), members):
        grouped = every.view(2, 3, *every.shape[1:])
        middle = grouped.sort(dim=1).values[:, 1]  # the median of three is the middle value
        torch.testing.assert_close(combined, middle, rtol=0, atol=0)
        assert not torch.equal(grouped[:, 0], grouped[:, 1])  # members start from different noise
    diffusion.config.sample_reduce = "mean"
    diffusion.config.sample_ensemble = 3  # the config's setting is the default
    depth_mean, _ = diffusion.sample(model, views, seed=4)
    torch.testing.assert_close(depth_mean, members[0].view(2, 3, 1, 18, 32).mean(dim=1))
    torch.testing.assert_close(diffusion.sample(model, views, seed=4)[0], depth_mean, rtol=0, atol=0)  # seeded
    with pytest.raises(ConfigError, match="sample_ensemble"):
        NDNDiffusionConfig(sample_ensemble=0).validate()
    with pytest.raises(ConfigError, match="sample_reduce"):
        NDNDiffusionConfig(sample_reduce="mode").validate()


def test_an_ensemble_samples_fewer_views_per_batch():
    from esgs.core.ndn.diffusion import GaussianDiffusion
    from esgs.core.ndn.infer import views_per_batch

    assert views_per_batch(4, GaussianDiffusion(NDNDiffusionConfig())) == 4
    assert views_per_batch(4, GaussianDiffusion(NDNDiffusionConfig(sample_ensemble=5))) == 1
    assert views_per_batch(8, GaussianDiffusion(NDNDiffusionConfig(sample_ensemble=3))) == 2
