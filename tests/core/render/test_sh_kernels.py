"""The fused Numba SH colours (core/render/sh_kernels.py) against the torch expression."""
from __future__ import annotations

import pytest
import torch

from esgs.core.render.sh import evaluate_sh_colors
from esgs.core.render.sh_kernels import fused_sh_colors


def _inputs(count, dtype, seed):
    generator = torch.Generator().manual_seed(seed)
    coefficients = (0.5 * torch.randn(count, 16, 3, generator=generator)).to(dtype)
    directions = (3.0 * torch.randn(count, 3, generator=generator)).to(dtype)
    directions[0] = 0.0  # a Gaussian at the camera centre: the 1e-12 floor
    directions[1] = torch.tensor([0.0, 0.0, 1e-14], dtype=dtype)
    coefficients[2, 0] = -10.0  # a colour clamped at 0 in every channel
    return coefficients.requires_grad_(), directions.requires_grad_()


def _gradients(function, coefficients, directions, weights):
    grads = torch.autograd.grad((function(coefficients, directions) * weights).sum(), [coefficients, directions],
                                allow_unused=True)
    return [g if g is not None else torch.zeros_like(x) for g, x in zip(grads, (coefficients, directions))]


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("dtype, tolerance", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_values_and_gradients_equal_the_torch_expression(degree, dtype, tolerance):
    coefficients, directions = _inputs(400, dtype, seed=degree)
    weights = torch.randn(400, 3, generator=torch.Generator().manual_seed(9)).to(dtype)
    fused = fused_sh_colors(degree, coefficients, directions)
    plain = evaluate_sh_colors(degree, coefficients, directions)
    torch.testing.assert_close(fused, plain, rtol=tolerance, atol=tolerance)
    assert float(fused[2].abs().max()) == 0.0
    grads = _gradients(lambda c, d: fused_sh_colors(degree, c, d), coefficients, directions, weights)
    expected = _gradients(lambda c, d: evaluate_sh_colors(degree, c, d), coefficients, directions, weights)
    for name, got, want in zip(("coefficients", "directions"), grads, expected):
        scale = max(float(want.abs().max()), 1.0)
        torch.testing.assert_close(got, want, rtol=tolerance, atol=tolerance * scale, msg=name)
    # the coefficients above (degree + 1)^2 take no gradient
    assert float(grads[0][:, (degree + 1) ** 2:].abs().max() if degree < 3 else 0.0) == 0.0


def test_gradients_match_finite_differences():
    generator = torch.Generator().manual_seed(4)
    coefficients = (0.3 * torch.randn(5, 16, 3, generator=generator)).double().requires_grad_()
    directions = torch.randn(5, 3, generator=generator).double().requires_grad_()
    assert torch.autograd.gradcheck(lambda c, d: fused_sh_colors(3, c, d), (coefficients, directions))


def test_the_cpu_backend_renders_with_it_and_equals_the_reference_backend():
    from esgs.core.render import rasterization

    generator = torch.Generator().manual_seed(1)
    count = 60
    means = torch.randn(count, 3, generator=generator) * 0.5 + torch.tensor([0.0, 0.0, 4.0])
    quats = torch.randn(count, 4, generator=generator)
    scales = torch.full((count, 3), 0.15)
    opacities = torch.full((count,), 0.7)
    colors = (0.4 * torch.randn(count, 16, 3, generator=generator)).requires_grad_()
    viewmat = torch.eye(4)[None]
    K = torch.tensor([[[40.0, 0.0, 20.0], [0.0, 40.0, 15.0], [0.0, 0.0, 1.0]]])
    images = {}
    for backend in ("cpu", "reference"):
        render, _, _ = rasterization(means, quats, scales, opacities, colors, viewmat, K, 40, 30, sh_degree=3,
                                     backend=backend)
        gradient = torch.autograd.grad(render.sum(), colors)[0]
        images[backend] = (render.detach(), gradient)
    torch.testing.assert_close(images["cpu"][0], images["reference"][0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(images["cpu"][1], images["reference"][1], rtol=1e-4, atol=1e-5)
