"""The dense reference rasterizer and the SH basis against closed forms and finite differences."""
from __future__ import annotations

import math

import pytest
import torch

from esgs.core.render import rasterization
from esgs.core.render.sh import evaluate_sh_colors, sh_basis

from .scenes import random_scene


def _fibonacci_sphere(count: int) -> tuple[torch.Tensor, float]:
    index = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * index / count
    radius = torch.sqrt(1.0 - z * z)
    angle = math.pi * (1.0 + math.sqrt(5.0)) * index
    points = torch.stack([radius * torch.cos(angle), radius * torch.sin(angle), z], -1)
    return points, 4.0 * math.pi / count


def test_sh_basis_is_orthonormal_on_the_sphere():
    points, area = _fibonacci_sphere(200_000)
    basis = sh_basis(3, points)  # [P, 16]
    gram = basis.T @ basis * area
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=2e-4)


def test_sh_matches_3dgs_sign_convention_for_degree_one():
    # With only the first degree-1 coefficient set, colour = 0.5 - c * Y1 * y.
    coefficients = torch.zeros(1, 4, 3, dtype=torch.float64)
    coefficients[0, 1] = torch.tensor([0.2, 0.0, -0.2])
    colour = evaluate_sh_colors(1, coefficients, torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64))
    expected = 0.5 - 0.2 * math.sqrt(3 / (4 * math.pi))
    assert torch.allclose(colour, torch.tensor([[expected, 0.5, max(0.0, 0.5 + 0.2 * math.sqrt(3 / (4 * math.pi)))]],
                                               dtype=torch.float64))


@pytest.mark.parametrize("backend", ["reference", "cpu"])
@pytest.mark.parametrize("antialiased", [False, True])
def test_single_gaussian_matches_closed_form(backend, antialiased):
    """One isotropic Gaussian on the optical axis: alpha(p) = o exp(-|p - c|^2 / (2 s^2)) with
    s^2 = (f sigma / z)^2 + dilation (and the antialiasing opacity factor)."""
    width, height, focal, depth, sigma, opacity = 33, 21, 40.0, 4.0, 0.12, 0.7
    means = torch.tensor([[0.0, 0.0, depth]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    scales = torch.tensor([[sigma, sigma, 0.01]], dtype=torch.float64)
    colors = torch.tensor([[0.2, 0.5, 0.9]], dtype=torch.float64)
    Ks = torch.tensor([[[focal, 0, 16.0], [0, focal, 10.0], [0, 0, 1]]], dtype=torch.float64)
    viewmats = torch.eye(4, dtype=torch.float64)[None]
    render, alpha, meta = rasterization(means, quats, scales, torch.tensor([opacity], dtype=torch.float64), colors,
                                        viewmats, Ks, width, height, render_depth=True, render_normals=True,
                                        antialiased=antialiased, eps2d=0.4, backend=backend)
    variance = (focal * sigma / depth) ** 2
    dilation = 0.4 if antialiased else 0.3
    effective = opacity * (variance / (variance + dilation) if antialiased else 1.0)
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                            torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
    expected = effective * torch.exp(-((xs - 16.0) ** 2 + (ys - 10.0) ** 2) / (2 * (variance + dilation)))
    expected = torch.where(expected >= 1 / 255, expected.clamp(max=0.99), torch.zeros_like(expected))
    assert torch.allclose(alpha[0, ..., 0], expected, atol=1e-12)
    assert torch.allclose(render[0, ..., :3], expected[..., None] * colors[0], atol=1e-12)
    hit = expected > 0
    assert torch.allclose(render[0, ..., 3][hit], torch.full_like(expected[hit], depth))
    assert torch.all(render[0, ..., 3][~hit] == 0)
    # Shortest axis is world z = camera z; facing the camera means pointing at -z.
    assert torch.allclose(render[0, ..., 4:7], expected[..., None] * torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))
    assert torch.allclose(meta["means2d"][0, 0], torch.tensor([16.0, 10.0], dtype=torch.float64))
    level = 2 * math.log(255 * effective)
    assert int(meta["radii"][0, 0]) == math.ceil(math.sqrt(level * (variance + dilation)))


def test_two_gaussians_composite_front_to_back():
    """A near red Gaussian over a far blue one: colour = a1 red + (1 - a1) a2 blue."""
    means = torch.tensor([[0.0, 0.0, 6.0], [0.0, 0.0, 3.0]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0], [0.0, 1.0, 0, 0]], dtype=torch.float64)
    scales = torch.full((2, 3), 0.5, dtype=torch.float64)
    opacities = torch.tensor([0.8, 0.6], dtype=torch.float64)
    colors = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    Ks = torch.tensor([[[10.0, 0, 2.0], [0, 10.0, 2.0], [0, 0, 1]]], dtype=torch.float64)
    render, alpha, _ = rasterization(means, quats, scales, opacities, colors, torch.eye(4, dtype=torch.float64)[None],
                                     Ks, 4, 4, render_depth=True, backend="reference")
    def gaussian(opacity, depth, offset):
        variance = (10.0 * 0.5 / depth) ** 2 + 0.3
        return opacity * math.exp(-offset / (2 * variance))
    offset = 0.5 ** 2 * 2  # pixel (1, 1) centre (1.5, 1.5) vs (2, 2)
    near, far = gaussian(0.6, 3.0, offset), gaussian(0.8, 6.0, offset)
    assert render[0, 1, 1, 0].item() == pytest.approx(near)
    assert render[0, 1, 1, 2].item() == pytest.approx((1 - near) * far)
    assert alpha[0, 1, 1, 0].item() == pytest.approx(1 - (1 - near) * (1 - far))
    expected_depth = (near * 3.0 + (1 - near) * far * 6.0) / (near + (1 - near) * far)
    assert render[0, 1, 1, 3].item() == pytest.approx(expected_depth)


def test_reference_gradients_match_finite_differences():
    scene = random_scene(5, seed=3, width=12, height=9, sh_degree=1, extra_dims=1, opacity_range=(0.2, 0.8),
                         scale_range=(0.4, 0.8))
    names = ("means", "quats", "scales", "opacities", "colors", "extra")

    def render(*tensors):
        values = dict(zip(names, tensors))
        image, alpha, _ = rasterization(values["means"], values["quats"], values["scales"], values["opacities"],
                                        values["colors"], scene["viewmats"], scene["Ks"], 12, 9, sh_degree=1,
                                        extra=values["extra"], render_depth=True, render_normals=True,
                                        antialiased=True, backend="reference")
        return image, alpha

    inputs = tuple(scene[name].clone().requires_grad_(True) for name in names)
    # fast_mode checks random projections of the Jacobian: one backward instead of one per output.
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


@pytest.mark.slow
def test_reference_handles_8k_gaussians_at_160x90():
    scene = random_scene(8192, seed=5, width=160, height=90, dtype=torch.float32)
    tensors = {name: scene[name].requires_grad_(True) for name in ("means", "quats", "scales", "opacities", "colors")}
    render, alpha, _ = rasterization(tensors["means"], tensors["quats"], tensors["scales"], tensors["opacities"],
                                     tensors["colors"], scene["viewmats"], scene["Ks"], 160, 90, render_depth=True,
                                     backend="reference")
    (render.sum() + alpha.sum()).backward()
    assert torch.isfinite(tensors["means"].grad).all()
    assert alpha.mean() > 0.5
