"""The training loss's D-SSIM kernels against the torch statement of SSIM (values, gradients, bits)."""
from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from esgs.core.metrics.image import SSIM_CONSTANTS, gaussian_window_1d, ssim_map
from esgs.core.train import ssim_kernels
from esgs.core.train.fused_ssim import _FusedDSSIM, dssim


def _reference(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return 1.0 - ssim_map(image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]).mean()


def _pair(height: int, width: int, channels: int, dtype: torch.dtype, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    target = torch.rand(height, width, channels, generator=generator, dtype=dtype)
    # an image near its target (as in training) and one far from it: both regimes of the formula
    image = (target + 0.1 * torch.randn(height, width, channels, generator=generator, dtype=dtype)).clamp(0, 1)
    return image, target


@pytest.mark.parametrize("shape", [(37, 53, 3), (270, 48, 3), (4, 3, 3), (12, 9, 1), (1, 1, 3)])
def test_values_and_gradients_equal_the_torch_statement_in_float64(shape):
    image, target = _pair(*shape, torch.float64)
    for candidate in (image, torch.rand(shape, dtype=torch.float64)):
        ours_input = candidate.clone().requires_grad_()
        theirs_input = candidate.clone().requires_grad_()
        ours, theirs = dssim(ours_input, target), _reference(theirs_input, target)
        assert ours.dtype == torch.float64
        assert float(ours.detach()) == pytest.approx(float(theirs.detach()), abs=1e-12)
        (ours * 2.5).backward()
        (theirs * 2.5).backward()  # the upstream gradient is applied
        np.testing.assert_allclose(ours_input.grad.numpy(), theirs_input.grad.numpy(), rtol=1e-9, atol=1e-15)


def test_float32_agrees_to_float_rounding():
    image, target = _pair(135, 240, 3, torch.float32, seed=3)
    ours_input, theirs_input = image.clone().requires_grad_(), image.clone().requires_grad_()
    ours, theirs = dssim(ours_input, target), _reference(theirs_input, target)
    assert ours.dtype == torch.float32
    assert float(ours.detach()) == pytest.approx(float(theirs.detach()), abs=1e-6)
    ours.backward()
    theirs.backward()
    scale = float(theirs_input.grad.abs().max())
    np.testing.assert_allclose(ours_input.grad.numpy(), theirs_input.grad.numpy(), atol=1e-4 * scale)


def test_gradcheck():
    image, target = _pair(14, 17, 3, torch.float64, seed=5)
    assert torch.autograd.gradcheck(lambda x: _FusedDSSIM.apply(x, target), (image.requires_grad_(),))


def test_identical_images_have_zero_loss_and_zero_gradient():
    image, _ = _pair(20, 30, 3, torch.float64)
    image.requires_grad_()
    loss = dssim(image, image.detach().clone())
    loss.backward()
    assert float(loss.detach()) == pytest.approx(0.0, abs=1e-12)
    assert float(image.grad.abs().max()) < 1e-12


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_same_bits_on_any_thread_count_and_block_size(dtype):
    rng = np.random.default_rng(2)
    x = rng.random((75, 31 * 3)).astype(dtype)
    y = rng.random((75, 31 * 3)).astype(dtype)
    taps = gaussian_window_1d(11, 1.5, dtype=torch.float64).numpy().astype(dtype)
    constants = np.asarray(SSIM_CONSTANTS, dtype)
    scale = np.asarray([-0.5], dtype)
    before = numba.get_num_threads()
    results = []
    try:
        for threads, block in ((1, 32), (2, 32), (2, 1), (2, 7), (numba.config.NUMBA_NUM_THREADS, 75)):
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            totals, dmu, dxx, dxy = ssim_kernels.ssim_forward(x, y, taps, 3, constants, block)
            grad = ssim_kernels.ssim_backward(x, y, dmu, dxx, dxy, taps, 3, scale, block)
            results.append((totals, dmu, dxx, dxy, grad))
    finally:
        numba.set_num_threads(before)
    for other in results[1:]:
        for first, second in zip(results[0], other):
            np.testing.assert_array_equal(first, second)


def test_torch_statement_where_the_kernels_do_not_apply():
    image, target = _pair(16, 16, 3, torch.float64)
    # a target that needs a gradient (the kernels give none to it): the torch statement, both gradients
    target = target.clone().requires_grad_()
    image = image.clone().requires_grad_()
    loss = dssim(image, target)
    loss.backward()
    assert target.grad is not None and float(target.grad.abs().max()) > 0
    assert float(loss.detach()) == pytest.approx(float(_reference(image.detach(), target.detach())), abs=1e-12)


def test_the_training_loss_term_is_this_d_ssim():
    from esgs.core.train.losses import LossContext, dssim_loss

    image, target = _pair(30, 40, 3, torch.float32, seed=7)
    image.requires_grad_()
    context = LossContext(step=1, image=image, target=target, mask=None, alpha=torch.ones(30, 40, 1))
    loss = dssim_loss(context)
    assert loss.grad_fn is not None and "FusedDSSIM" in type(loss.grad_fn).__name__
    assert float(loss.detach()) == pytest.approx(float(_reference(image.detach(), target)), abs=1e-6)
