"""PSNR and SSIM against independent numpy/scipy references, identities and gradients."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from esgs.core.errors import ESGSError
from esgs.core.metrics.image import gaussian_window_1d, psnr, ssim, ssim_map


def _ssim_map_scipy(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Independent SSIM: scipy's Gaussian filter, 11 taps (radius = int(truncate*sigma+0.5) = 5),
    zero padding outside the image, per channel. x, y: [C, H, W] float64."""
    sigma, truncate = 1.5, 5.0 / 1.5
    blur = lambda a: np.stack([gaussian_filter(c, sigma, mode="constant", cval=0.0, truncate=truncate) for c in a])  # noqa: E731
    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    return ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))


def _pair(seed: int, shape=(2, 3, 24, 31)) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    ref = torch.rand(shape, generator=g, dtype=torch.float64)
    img = (ref + 0.15 * torch.randn(shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    return img, ref


def test_window_matches_definition():
    taps = gaussian_window_1d(11, 1.5, dtype=torch.float64)
    expected = np.exp(-(np.arange(-5, 6) ** 2) / (2 * 1.5**2))
    np.testing.assert_allclose(taps.numpy(), expected / expected.sum(), rtol=1e-14)


def test_ssim_map_matches_scipy_reference():
    img, ref = _pair(0)
    ours = ssim_map(img, ref).numpy()
    for b in range(img.shape[0]):
        expected = _ssim_map_scipy(img[b].numpy(), ref[b].numpy())
        np.testing.assert_allclose(ours[b], expected, rtol=1e-9, atol=1e-11)
    # float32 (the training dtype) agrees to single precision
    ours32 = ssim(img.float(), ref.float()).item()
    assert ours32 == pytest.approx(float(np.mean([_ssim_map_scipy(i.numpy(), r.numpy()) for i, r in zip(img, ref)])), abs=2e-6)


def test_ssim_identities_and_analytic_case():
    img, ref = _pair(1)
    np.testing.assert_allclose(ssim_map(ref, ref).numpy(), 1.0, rtol=1e-12)  # everywhere, borders included
    assert ssim(ref.float(), ref.float()).item() == pytest.approx(1.0, abs=1e-6)
    # constant images a and b: away from the zero-padded border both variances vanish, so
    # SSIM = (2ab + C1) / (a^2 + b^2 + C1)
    a, b = 0.3, 0.7
    x = torch.full((1, 3, 20, 20), a, dtype=torch.float64)
    y = torch.full((1, 3, 20, 20), b, dtype=torch.float64)
    interior = ssim_map(x, y)[..., 5:-5, 5:-5]
    c1 = 0.01**2
    np.testing.assert_allclose(interior.numpy(), (2 * a * b + c1) / (a * a + b * b + c1), rtol=1e-10)
    # symmetric, below 1 for different images, and 3-D input treated as a batch of one
    assert ssim(img, ref).item() == pytest.approx(ssim(ref, img).item(), rel=1e-12)
    assert ssim(img, ref).item() < 0.99
    assert ssim(img[0], ref[0]).item() == pytest.approx(ssim(img[:1], ref[:1]).item(), rel=1e-12)
    per_image = ssim(img, ref, reduction="none")
    assert per_image.shape == (2,) and per_image.mean().item() == pytest.approx(ssim(img, ref).item(), rel=1e-12)


def test_ssim_gradient_matches_finite_differences():
    """Autograd against central differences (float64): along random directions over the whole
    image, and per pixel at corners, edges and the interior (where the padding matters)."""
    img, ref = _pair(2, shape=(2, 3, 16, 19))
    img.requires_grad_(True)
    ssim(img, ref).backward()
    grad = img.grad.clone()
    eps = 1e-6

    def at(x: torch.Tensor) -> float:
        with torch.no_grad():
            return ssim(x, ref).item()

    g = torch.Generator().manual_seed(3)
    for _ in range(4):
        direction = torch.randn(img.shape, generator=g, dtype=torch.float64)
        numeric = (at(img + eps * direction) - at(img - eps * direction)) / (2 * eps)
        assert numeric == pytest.approx(float((grad * direction).sum()), rel=1e-6, abs=1e-9)
    for index in [(0, 0, 0, 0), (1, 2, 15, 18), (0, 1, 0, 9), (1, 0, 8, 9), (0, 2, 4, 4)]:
        bump = torch.zeros_like(img)
        bump[index] = eps
        numeric = (at(img + bump) - at(img - bump)) / (2 * eps)
        assert numeric == pytest.approx(grad[index].item(), rel=1e-5, abs=1e-10)
    # a tiny full Jacobian check with a different window, through torch's own tool
    small, small_ref = _pair(4, shape=(1, 2, 6, 7))
    small.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: ssim(x, small_ref, window_size=5, sigma=1.0), (small,), eps=1e-6, atol=1e-7)


def test_psnr_values():
    ref = torch.zeros(2, 3, 8, 8, dtype=torch.float64)
    img = ref.clone()
    img[0] += 0.1  # MSE 0.01 -> 20 dB
    img[1, :, :4] += 0.5  # half the pixels off by 0.5: MSE 0.125 -> 9.0309 dB
    per_image = psnr(img, ref, reduction="none")
    np.testing.assert_allclose(per_image.numpy(), [20.0, -10 * math.log10(0.125)], rtol=1e-12)
    assert psnr(img, ref).item() == pytest.approx(per_image.mean().item(), rel=1e-12)
    assert psnr(img[0], ref[0]).item() == pytest.approx(20.0, rel=1e-12)
    assert math.isinf(psnr(ref, ref).item())


def test_bad_inputs_raise_our_error():
    with pytest.raises(ESGSError, match="shapes differ"):
        psnr(torch.zeros(3, 4, 4), torch.zeros(3, 4, 5))
    with pytest.raises(ESGSError, match="B, C, H, W"):
        ssim(torch.zeros(4, 4), torch.zeros(4, 4))
    with pytest.raises(ESGSError, match="odd"):
        ssim(torch.zeros(3, 4, 4), torch.zeros(3, 4, 4), window_size=4)
    with pytest.raises(ESGSError, match="reduction"):
        psnr(torch.zeros(3, 4, 4), torch.ones(3, 4, 4), reduction="sum")
