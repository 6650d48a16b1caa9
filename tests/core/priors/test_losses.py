"""Prior loss terms: gradients, masks, alignment and geometry checked against known answers."""
from __future__ import annotations

import math

import pytest
import torch

from esgs.core.priors import losses


def _plane_depth(height=12, width=16, tilt=0.3, distance=5.0, dtype=torch.float64):
    """Depth of the plane n.X = d seen by a pinhole camera, and K, and the plane normal."""
    K = torch.tensor([[20.0, 0, width / 2], [0, 22.0, height / 2], [0, 0, 1]], dtype=dtype)
    normal = torch.tensor([0.0, math.sin(tilt), -math.cos(tilt)], dtype=dtype)  # faces the camera
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype), torch.arange(width, dtype=dtype), indexing="ij")
    rays = torch.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    # plane: normal . X = -distance  (X = t * ray, depth = t)
    depth = -distance / (rays @ normal)
    return depth, K, normal


def test_normals_from_depth_recover_a_tilted_plane():
    depth, K, normal = _plane_depth()
    estimated, valid = losses.normals_from_depth(depth, K)
    assert valid.sum() == (depth.shape[0] - 2) * (depth.shape[1] - 2)
    cos = (estimated[valid] @ normal)
    assert torch.all(cos > 1 - 1e-9)


def test_depth_normal_consistency_is_zero_when_consistent_and_positive_otherwise():
    depth, K, normal = _plane_depth()
    consistent = normal.expand(*depth.shape, 3).clone()
    assert losses.depth_normal_consistency_loss(depth, consistent, K).item() == pytest.approx(0.0, abs=1e-9)
    wrong = torch.tensor([0.0, 0.0, -1.0], dtype=depth.dtype).expand(*depth.shape, 3)
    expected = 1 - (-normal[2]).item()  # cos between (0,0,-1) and the plane normal
    assert losses.depth_normal_consistency_loss(depth, wrong, K).item() == pytest.approx(expected, rel=1e-6)


def test_scale_shift_fit_recovers_known_transform_despite_outliers():
    generator = torch.Generator().manual_seed(0)
    pred = torch.rand(40, 50, generator=generator, dtype=torch.float64) * 10 + 1
    target = 2.5 * pred - 0.75
    mask = torch.ones_like(pred, dtype=torch.bool)
    outliers = torch.rand(pred.shape, generator=generator) < 0.05
    corrupted = torch.where(outliers, target + 40.0, target)
    scale, shift = losses.fit_scale_shift(pred, corrupted, mask)
    assert scale.item() == pytest.approx(2.5, rel=1e-6)
    assert shift.item() == pytest.approx(-0.75, abs=1e-5)
    # masked-out pixels do not take part
    masked = torch.where(mask & ~outliers, target, torch.full_like(target, 1e6))
    scale2, shift2 = losses.fit_scale_shift(pred, masked, ~outliers)
    assert (scale2.item(), shift2.item()) == pytest.approx((2.5, -0.75), rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("mode", ["log", "inverse"])
def test_depth_loss_gradient_matches_finite_differences(mode):
    generator = torch.Generator().manual_seed(1)
    rendered = (torch.rand(6, 7, generator=generator, dtype=torch.float64) + 1).requires_grad_()
    prior = torch.rand(6, 7, generator=generator, dtype=torch.float64) * 3 + 1
    mask = torch.rand(6, 7, generator=generator) > 0.2
    weights = torch.rand(6, 7, generator=generator, dtype=torch.float64)
    func = lambda r: losses.depth_loss(r, prior, mask, weights, mode=mode)
    assert torch.autograd.gradcheck(func, (rendered,), eps=1e-6, atol=1e-6)


def test_the_robust_depth_error_pulls_far_pixels_less_and_matches_its_closed_form():
    rendered = torch.tensor([[2.0, 2.0, 2.0]], dtype=torch.float64, requires_grad=True)
    prior = torch.tensor([[2.0 * math.exp(0.01), 2.0 * math.exp(0.5), 2.0 * math.exp(2.0)]], dtype=torch.float64)
    mask = torch.ones(1, 3, dtype=torch.bool)
    plain = losses.depth_loss(rendered, prior, mask)
    robust = losses.depth_loss(rendered, prior, mask, robust=0.1)
    errors = torch.tensor([0.01, 0.5, 2.0], dtype=torch.float64)
    assert float(plain) == pytest.approx(float(errors.mean()))
    assert float(robust) == pytest.approx(float((0.1 * torch.log1p(errors / 0.1)).mean()))
    robust.backward()
    # the pull on each pixel is the L1 pull (1/3 per pixel of d log r / dr = 1/2) times 1 / (1 + e / s)
    expected = -(1.0 / 3.0) * 0.5 / (1.0 + errors / 0.1)
    assert torch.allclose(rendered.grad[0], expected)
    func = lambda r: losses.depth_loss(r, prior, mask, robust=0.3, mode="inverse")  # noqa: E731
    assert torch.autograd.gradcheck(func, (rendered.detach().clone().requires_grad_(),), eps=1e-6, atol=1e-6)


def test_normal_loss_gradient_and_zero_at_match():
    generator = torch.Generator().manual_seed(2)
    rendered = torch.randn(5, 6, 3, generator=generator, dtype=torch.float64).requires_grad_()
    prior = torch.randn(5, 6, 3, generator=generator, dtype=torch.float64)
    prior = prior / prior.norm(dim=-1, keepdim=True)
    mask = torch.ones(5, 6, dtype=torch.bool)
    assert torch.autograd.gradcheck(lambda r: losses.normal_loss(r, prior, mask), (rendered,), eps=1e-6, atol=1e-6)
    assert losses.normal_loss(prior * 0.7, prior, mask).item() == pytest.approx(0.0, abs=1e-12)
    # opposite normals: L1 = 2 * sum|n| per pixel, angular = 2
    expected = (2 * prior.abs().sum(-1) + 2).mean().item()
    assert losses.normal_loss(-prior, prior, mask).item() == pytest.approx(expected, rel=1e-9)


def test_masked_pixels_never_contribute():
    generator = torch.Generator().manual_seed(3)
    rendered = torch.rand(8, 8, generator=generator) + 1
    prior = torch.rand(8, 8, generator=generator) + 1
    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[:4] = True  # the bottom half is "sky"
    base = losses.depth_loss(rendered, prior, mask)
    sky_changed = prior.clone()
    sky_changed[4:] = 1000.0
    assert losses.depth_loss(rendered, sky_changed, mask).item() == base.item()
    rendered_normal = torch.randn(8, 8, 3, generator=generator)
    prior_normal = torch.randn(8, 8, 3, generator=generator)
    base_n = losses.normal_loss(rendered_normal, prior_normal, mask)
    prior_normal[4:] = torch.tensor([1.0, 0.0, 0.0])
    assert losses.normal_loss(rendered_normal, prior_normal, mask).item() == base_n.item()
    # empty mask: zero loss, still differentiable
    empty = torch.zeros_like(mask)
    r = rendered.clone().requires_grad_()
    value = losses.depth_loss(r, prior, empty)
    value.backward()
    assert value.item() == 0.0 and torch.all(r.grad == 0)


def test_relative_depth_prior_aligned_gives_zero_loss():
    rendered = torch.rand(10, 10, dtype=torch.float64) * 4 + 2
    prior = (rendered - 0.5) / 3.0  # relative prior: rendered = 3 * prior + 0.5
    mask = torch.ones_like(rendered, dtype=torch.bool)
    assert losses.depth_loss(rendered, prior, mask, relative=True).item() == pytest.approx(0.0, abs=1e-9)
    assert losses.depth_loss(rendered, prior, mask, relative=False).item() > 0.1


def test_edge_aware_weights_are_low_on_edges_and_one_on_flat_regions():
    image = torch.zeros(10, 10, 3)
    image[:, 5:] = 1.0
    weights = losses.edge_aware_weights(image, edge_strength=10.0)
    assert weights[:, :3].min().item() == 1.0 and weights[:, 6:].min().item() == 1.0
    assert weights[:, 4].max().item() == pytest.approx(math.exp(-10.0), rel=1e-5)


def test_unknown_mode_is_rejected():
    with pytest.raises(ValueError, match="unknown depth loss mode"):
        losses.depth_loss(torch.ones(2, 2), torch.ones(2, 2), torch.ones(2, 2, dtype=torch.bool), mode="abs")


def test_sky_loss_gradient_matches_finite_differences_in_depth_and_leaves_alpha_alone():
    generator = torch.Generator().manual_seed(3)
    depth = (torch.rand(6, 7, generator=generator, dtype=torch.float64) * 8 + 1).requires_grad_()
    alpha = torch.rand(6, 7, generator=generator, dtype=torch.float64).requires_grad_()
    sky = torch.rand(6, 7, generator=generator) > 0.4
    # far = 6: about half the sky pixels are nearer (penalised), half beyond (free); none sits
    # on the hinge's kink, where finite differences would be ill-defined
    assert ((depth - 6).abs() > 1e-3).all()
    assert torch.autograd.gradcheck(lambda d: losses.sky_loss(d, alpha.detach(), sky, 6.0), (depth,), eps=1e-6, atol=1e-6)
    # alpha only weights the push: the loss moves sky painters back, it never makes them transparent
    losses.sky_loss(depth, alpha, sky, 6.0).backward()
    assert alpha.grad is None or torch.count_nonzero(alpha.grad) == 0
    penalised = sky & (depth.detach() < 6.0)
    assert penalised.any() and (depth.grad[penalised] < 0).all()  # descent moves them farther
    assert (depth.grad[~penalised] == 0).all()


def test_sky_loss_counts_only_near_covered_sky_pixels():
    depth = torch.tensor([[2.0, 8.0], [2.0, 2.0]], dtype=torch.float64)
    alpha = torch.tensor([[0.5, 1.0], [0.0, 1.0]], dtype=torch.float64)
    sky = torch.tensor([[True, True], [True, False]])
    # pixel (0,0): 0.5 * log(4 / 2); (0,1) beyond the far surface; (1,0) empty; (1,1) is no sky
    expected = 0.5 * math.log(2.0) / 3
    assert losses.sky_loss(depth, alpha, sky, 4.0).item() == pytest.approx(expected, rel=1e-12)
    assert losses.sky_loss(depth, alpha, torch.zeros_like(sky), 4.0).item() == 0.0
    assert losses.sky_loss(depth * 10, alpha, sky, 4.0).item() == 0.0


def test_thinness_loss_is_the_weighted_mean_over_pixels_with_a_prior_normal():
    from esgs.core.priors.losses import thinness_loss

    thickness = torch.tensor([[0.5, 2.0], [1.0, 3.0]])
    normal = torch.zeros(2, 2, 3)
    normal[..., 2] = -1.0
    normal[1, 1] = 0.0  # no prior normal here: never counts
    mask = torch.tensor([[True, True], [False, True]])
    weights = torch.tensor([[1.0, 3.0], [1.0, 1.0]])
    confidence = torch.tensor([[0.5, 1.0], [1.0, 1.0]])
    loss = thinness_loss(thickness, normal, mask, weights, confidence=confidence)
    assert float(loss) == pytest.approx((1.0 * 0.5 * 0.5 + 3.0 * 2.0) / 4.0)
    assert float(thinness_loss(thickness, normal, torch.zeros_like(mask))) == 0.0


def test_incidence_weights_follow_the_cosine_between_ray_and_prior_normal():
    """(|n . r| / c)^2 capped at 1, against a per-pixel computation from K; unknown normals weigh 1."""
    generator = torch.Generator().manual_seed(3)
    height, width = 5, 7
    K = torch.tensor([[40.0, 0.0, 3.2], [0.0, 38.0, 2.6], [0.0, 0.0, 1.0]])
    normal = torch.randn(height, width, 3, generator=generator)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    normal[0, 0] = 0.0  # no prior normal there
    cosine = 0.4
    weights = losses.incidence_weights(normal, K, cosine)
    assert weights.shape == (height, width)
    for i in range(height):
        for j in range(width):
            if i == 0 and j == 0:
                assert weights[i, j] == 1.0
                continue
            ray = torch.tensor([(j + 0.5 - 3.2) / 40.0, (i + 0.5 - 2.6) / 38.0, 1.0])
            cos = abs(float(ray @ normal[i, j])) / float(ray.norm())
            assert float(weights[i, j]) == pytest.approx(min(1.0, (cos / cosine) ** 2), rel=1e-5)
    # a surface facing the camera keeps its full weight
    facing = torch.zeros(height, width, 3)
    facing[..., 2] = -1.0
    assert bool((losses.incidence_weights(facing, torch.tensor([[1e4, 0, 3.5], [0, 1e4, 2.5], [0, 0, 1.0]]),
                                          cosine) == 1.0).all())
