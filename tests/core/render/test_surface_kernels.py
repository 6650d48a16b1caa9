"""The Numba thinness kernel against the torch expression it replaces on the CPU (values and gradients)."""
from __future__ import annotations

import pytest
import torch

from esgs.core.render.projection import quaternion_to_matrix
from esgs.core.render.surface import median_surface_thinness


def _case(dtype: torch.dtype, id_dtype: torch.dtype = torch.long, seed: int = 0):
    """Many Gaussians with every edge case: ids of no Gaussian, a pixel without a prior normal,
    a zero quaternion (below the normalisation floor), a Gaussian with zero scales (the mean
    variance floor), a Gaussian drawn by many pixels (its gradients add up)."""
    generator = torch.Generator().manual_seed(seed)
    count, height, width = 40, 9, 13
    quats = torch.randn(count, 4, generator=generator, dtype=dtype)
    quats[3] = 0.0
    scales = torch.rand(count, 3, generator=generator, dtype=dtype) * 2.0 + 0.01
    scales[7] = 0.0
    ids = torch.randint(-1, count, (height, width), generator=generator).to(id_dtype)
    ids[2:6, 3:9] = 11
    ids[0, 0], ids[0, 1], ids[0, 2] = 3, 7, -1
    normals = torch.randn(height, width, 3, generator=generator, dtype=dtype)
    normals[1, 1] = 0.0
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[:3, :3] = quaternion_to_matrix(torch.randn(1, 4, generator=generator, dtype=dtype))[0]
    viewmat[:3, 3] = torch.randn(3, generator=generator, dtype=dtype)
    weights = torch.randn(height, width, generator=generator, dtype=dtype)
    return ids, quats, scales, viewmat, normals, weights


def _values_and_gradients(fused: bool, ids, quats, scales, viewmat, normals, weights):
    quats, scales = quats.clone().requires_grad_(), scales.clone().requires_grad_()
    thick, valid = median_surface_thinness(ids, quats, scales, viewmat, normals, fused=fused)
    (thick * weights).sum().backward()
    return thick.detach(), valid, quats.grad, scales.grad


@pytest.mark.parametrize("id_dtype", [torch.long, torch.int32])
def test_the_kernel_gives_the_torch_expressions_values_and_gradients_in_float64(id_dtype):
    case = _case(torch.float64, id_dtype)
    fused = _values_and_gradients(True, *case)
    reference = _values_and_gradients(False, *case)
    assert torch.equal(fused[1], reference[1])
    for ours, theirs in zip((fused[0], fused[2], fused[3]), (reference[0], reference[2], reference[3])):
        assert ours.dtype == theirs.dtype and ours.shape == theirs.shape
        torch.testing.assert_close(ours, theirs, rtol=1e-10, atol=1e-10 * float(theirs.abs().max()))
    assert float(fused[0][case[0] < 0].abs().max()) == 0.0  # no Gaussian: 0, as the torch expression
    assert float(fused[2][11].abs().sum()) > 0.0  # the Gaussian of a whole patch collects its pixels' gradients


def test_the_kernel_agrees_in_float32_and_matches_finite_differences():
    case = _case(torch.float32, seed=1)
    fused = _values_and_gradients(True, *case)
    reference = _values_and_gradients(False, *case)
    for ours, theirs in zip((fused[0], fused[3]), (reference[0], reference[3])):
        assert ours.dtype == torch.float32
        torch.testing.assert_close(ours, theirs, rtol=1e-4, atol=1e-5)
    # quaternion gradients of the Gaussians away from the floors (below them the gradient is ~1e12)
    torch.testing.assert_close(fused[2][:3], reference[2][:3], rtol=1e-4, atol=1e-5)

    ids, quats, scales, viewmat, normals, _ = _case(torch.float64, seed=2)
    quats[3] = torch.tensor([1.0, 0.2, 0.0, 0.0], dtype=torch.float64)  # gradcheck stays off the floors
    scales[7] = 0.5

    def thinness(q, s):
        return median_surface_thinness(ids, q, s, viewmat, normals, fused=True)[0]

    assert torch.autograd.gradcheck(thinness, (quats.requires_grad_(), scales.requires_grad_()), eps=1e-6, atol=1e-6)


def test_the_kernels_gradients_are_the_same_on_every_run():
    case = _case(torch.float32, seed=3)
    first = _values_and_gradients(True, *case)
    second = _values_and_gradients(True, *case)
    assert all(torch.equal(a, b) for a, b in zip(first, second))
