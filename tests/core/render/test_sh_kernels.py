"""The fused Numba SH colours (core/render/sh_kernels.py) against the torch expression."""
from __future__ import annotations

import pytest
import torch

from esgs.core.render.sh import SHCoefficients, evaluate_sh_colors
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


@pytest.mark.parametrize("degree", [0, 1, 3])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_split_coefficients_give_the_concatenations_values_and_gradients(degree, dtype):
    """SHCoefficients (a trainer's sh_dc and sh_rest) read in place: the same colours, and the
    gradients of dc and rest are the concatenation's gradient cut at the degree-0 column."""
    coefficients, directions = _inputs(300, dtype, seed=10 + degree)
    weights = torch.randn(300, 3, generator=torch.Generator().manual_seed(3)).to(dtype)
    dc = coefficients.detach()[:, :1].clone().requires_grad_()
    rest = coefficients.detach()[:, 1:].clone().requires_grad_()
    split = fused_sh_colors(degree, SHCoefficients(dc, rest), directions)
    whole = fused_sh_colors(degree, coefficients, directions)
    assert torch.equal(split, whole)  # the same sums in the same order
    grad_dc, grad_rest, grad_directions = torch.autograd.grad((split * weights).sum(), [dc, rest, directions])
    grad_whole, grad_directions_whole = torch.autograd.grad((whole * weights).sum(), [coefficients, directions])
    assert grad_dc.shape == dc.shape and grad_rest.shape == rest.shape
    assert grad_dc.is_contiguous() and grad_rest.is_contiguous()
    assert torch.equal(grad_dc, grad_whole[:, :1]) and torch.equal(grad_rest, grad_whole[:, 1:])
    assert torch.equal(grad_directions, grad_directions_whole)
    # the torch expression (other backends) takes them too, concatenated
    torch.testing.assert_close(evaluate_sh_colors(degree, SHCoefficients(dc, rest), directions), whole,
                               rtol=2e-5, atol=2e-5)


def test_split_coefficients_match_finite_differences():
    generator = torch.Generator().manual_seed(6)
    dc = (0.3 * torch.randn(5, 1, 3, generator=generator)).double().requires_grad_()
    rest = (0.3 * torch.randn(5, 15, 3, generator=generator)).double().requires_grad_()
    directions = torch.randn(5, 3, generator=generator).double().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, d: fused_sh_colors(3, SHCoefficients(a, b), d), (dc, rest, directions))


def _scene(count=60, seed=1):
    generator = torch.Generator().manual_seed(seed)
    means = torch.randn(count, 3, generator=generator) * 0.5 + torch.tensor([0.0, 0.0, 4.0])
    quats = torch.randn(count, 4, generator=generator)
    scales = torch.full((count, 3), 0.15)
    opacities = torch.full((count,), 0.7)
    colors = 0.4 * torch.randn(count, 16, 3, generator=generator)
    viewmat = torch.eye(4)[None]
    K = torch.tensor([[[40.0, 0.0, 20.0], [0.0, 40.0, 15.0], [0.0, 0.0, 1.0]]])
    return means, quats, scales, opacities, colors, viewmat, K


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_rasterization_takes_split_coefficients_and_renders_what_the_tensor_renders(backend):
    from esgs.core.render import rasterization

    means, quats, scales, opacities, colors, viewmat, K = _scene()
    whole = colors.clone().requires_grad_()
    dc = colors[:, :1].clone().requires_grad_()
    rest = colors[:, 1:].clone().requires_grad_()
    weights = torch.rand(1, 30, 40, 3, generator=torch.Generator().manual_seed(2))
    outputs = {}
    for name, given, leaves in (("whole", whole, [whole]), ("split", SHCoefficients(dc, rest), [dc, rest])):
        render, _, _ = rasterization(means, quats, scales, opacities, given, viewmat, K, 40, 30, sh_degree=3,
                                     backend=backend)
        outputs[name] = (render.detach(), torch.autograd.grad((render * weights).sum(), leaves))
    torch.testing.assert_close(outputs["split"][0], outputs["whole"][0], rtol=1e-6, atol=1e-7)
    grad_dc, grad_rest = outputs["split"][1]
    (grad_whole,) = outputs["whole"][1]
    torch.testing.assert_close(torch.cat([grad_dc, grad_rest], dim=1), grad_whole, rtol=1e-6, atol=1e-7)
    assert float(grad_rest.abs().max()) > 0.0


def test_rasterization_refuses_split_coefficients_of_the_wrong_shape_or_without_a_degree():
    from esgs.core.errors import ConfigError
    from esgs.core.render import rasterization

    means, quats, scales, opacities, colors, viewmat, K = _scene(count=8)
    with pytest.raises(ConfigError, match="SHCoefficients have dc"):
        rasterization(means, quats, scales, opacities, SHCoefficients(colors[:, :2], colors[:, 2:]), viewmat, K,
                      40, 30, sh_degree=3)
    with pytest.raises(ConfigError, match="expected \\[N, K>=16"):
        rasterization(means, quats, scales, opacities, SHCoefficients(colors[:, :1], colors[:, 1:9]), viewmat, K,
                      40, 30, sh_degree=3)
    with pytest.raises(ConfigError, match="need sh_degree"):
        rasterization(means, quats, scales, opacities, SHCoefficients(colors[:, :1], colors[:, 1:]), viewmat, K,
                      40, 30)
    with pytest.raises(ConfigError, match="colors.dc must be a torch.Tensor"):
        rasterization(means, quats, scales, opacities, SHCoefficients(colors[:, :1].numpy(), colors[:, 1:]),
                      viewmat, K, 40, 30, sh_degree=3)
    with pytest.raises(ConfigError, match="share one dtype"):
        rasterization(means, quats, scales, opacities, SHCoefficients(colors[:, :1].double(), colors[:, 1:]),
                      viewmat, K, 40, 30, sh_degree=3)
