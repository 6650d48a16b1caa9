"""NDN network: output shapes, size, learning, weights on disk, deterministic sampling."""
from __future__ import annotations

import torch

from esgs.core.ndn.config import NDNConfig
from esgs.core.ndn.model import NDNUNet, parameter_count, timestep_embedding
from esgs.core.ndn.train import build_model, load_checkpoint, save_checkpoint

from .conftest import tiny_config


def _batch(config, batch=2, seed=0):
    generator = torch.Generator().manual_seed(seed)
    height, width = 16, 24
    views = torch.rand((batch, 9, height, width), generator=generator) * 2 - 1
    depth = torch.rand((batch, 1, height, width), generator=generator) * 2 - 1
    normal = torch.nn.functional.normalize(torch.randn((batch, 3, height, width), generator=generator), dim=1)
    return views, depth, normal


def test_output_shapes_and_default_size():
    model = NDNUNet(NDNConfig().model)
    assert 1_000_000 < parameter_count(model) <= 5_000_000
    views = torch.randn(2, 9, 32, 48)
    depth_out, normal_out = model(views, torch.randn(2, 1, 32, 48), torch.randn(2, 3, 32, 48), torch.tensor([3, 900]))
    assert depth_out.shape == (2, 1, 32, 48) and normal_out.shape == (2, 3, 32, 48)
    embedding = timestep_embedding(torch.tensor([0, 10]), 16)
    assert embedding.shape == (2, 16)
    torch.testing.assert_close(embedding[0, :8], torch.zeros(8))  # sin(0)
    torch.testing.assert_close(embedding[0, 8:], torch.ones(8))  # cos(0)


def test_normal_branch_uses_fine_image_features_only_in_the_last_steps():
    config = tiny_config()
    torch.manual_seed(0)
    model, _ = build_model(config)
    for parameter in model.normal_branch.output.parameters():  # zero-initialised: give it a response
        torch.nn.init.normal_(parameter, std=0.1)
    views, _, normal = _batch(config, batch=1)
    refine = model.refine_below

    def normal_output(t, perturb_fine):
        def hook(module, inputs, features):
            if perturb_fine:  # change the full-resolution image features only
                features = [features[0] + 0.5 * torch.randn_like(features[0])] + list(features[1:])
            return features

        handle = model.encoder.register_forward_hook(hook)
        try:
            with torch.no_grad():
                return model(views, normal[:, :1], normal, torch.tensor([t]))[1]
        finally:
            handle.remove()

    torch.manual_seed(1)
    # the noisiest steps (t >= refine_below) see only coarse image features: no change at all
    torch.testing.assert_close(normal_output(refine, False), normal_output(refine, True), rtol=0, atol=0)
    # the last T - N steps fuse full-resolution image features
    assert (normal_output(refine - 1, False) - normal_output(refine - 1, True)).abs().max() > 1e-3


def test_a_few_optimiser_steps_lower_the_loss_on_a_fixed_batch():
    config = tiny_config()
    torch.manual_seed(0)
    model, diffusion = build_model(config)
    views, depth, normal = _batch(config, batch=4)
    timesteps = torch.tensor([5, 15, 30, 45])

    def loss_value():
        return diffusion.training_loss(model, views, depth, normal, generator=torch.Generator().manual_seed(1),
                                       timesteps=timesteps)[0]

    before = float(loss_value().detach())
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)
    for _ in range(10):
        loss = loss_value()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = float(loss_value().detach())
    assert after < 0.95 * before


def test_weights_round_trip_and_deterministic_sampling(tmp_path):
    config = tiny_config(prediction="v")
    torch.manual_seed(3)
    model, diffusion = build_model(config)
    for parameter in model.parameters():  # make the zero-initialised heads matter
        parameter.data.add_(0.01 * torch.randn_like(parameter))
    path = save_checkpoint(tmp_path / "w.pt", model, config, step=7)
    loaded, loaded_diffusion, loaded_config, payload = load_checkpoint(path)
    assert payload["step"] == 7 and loaded_config == config
    views, depth, normal = _batch(config)
    t = torch.tensor([4, 40])
    model.eval()
    with torch.no_grad():
        for original, restored in zip(model(views, depth, normal, t), loaded(views, depth, normal, t)):
            torch.testing.assert_close(original, restored, rtol=0, atol=0)
    first = loaded_diffusion.sample(loaded, views, seed=5)
    second = loaded_diffusion.sample(loaded, views, seed=5)
    other = loaded_diffusion.sample(loaded, views, seed=6)
    for a, b, c in zip(first, second, other):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
        assert (a - c).abs().max() > 1e-4
    assert first[0].shape == (2, 1, 16, 24) and first[1].shape == (2, 3, 16, 24)
    assert first[0].abs().max() <= 1.0
