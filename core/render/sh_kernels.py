"""Spherical-harmonics colours in one Numba pass per Gaussian, forward and backward.

The torch expression of :func:`.sh.evaluate_sh_colors` builds some forty [N] temporaries for
the basis, and autograd keeps most of them for the backward (~0.2 KiB a Gaussian at degree 3).
Here the forward keeps nothing but its inputs and the backward recomputes the basis and its
derivatives per Gaussian. Same basis, signs and constants as :func:`.sh.sh_basis`; the tests
compare values and gradients with the torch expression and with finite differences.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from .sh import _Y00, _Y1, _Y2_XX_YY, _Y2_XY, _Y2_Z2, _Y3_A, _Y3_B, _Y3_C, _Y3_D, _Y3_E, num_sh_bases

_NORM_FLOOR = 1e-12  # as the torch expression: directions / max(|d|, 1e-12)


@njit(cache=True, inline="always")
def _basis(x, y, z, count, out):
    out[0] = _Y00
    if count > 1:
        out[1] = -_Y1 * y
        out[2] = _Y1 * z
        out[3] = -_Y1 * x
    if count > 4:
        xx, yy, zz = x * x, y * y, z * z
        out[4] = _Y2_XY * x * y
        out[5] = -_Y2_XY * y * z
        out[6] = _Y2_Z2 * (2.0 * zz - xx - yy)
        out[7] = -_Y2_XY * x * z
        out[8] = _Y2_XX_YY * (xx - yy)
        if count > 9:
            out[9] = -_Y3_A * y * (3.0 * xx - yy)
            out[10] = _Y3_B * x * y * z
            out[11] = -_Y3_C * y * (4.0 * zz - xx - yy)
            out[12] = _Y3_D * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            out[13] = -_Y3_C * x * (4.0 * zz - xx - yy)
            out[14] = _Y3_E * z * (xx - yy)
            out[15] = -_Y3_A * x * (xx - 3.0 * yy)


@njit(cache=True, inline="always")
def _basis_gradient(x, y, z, count, g, out):
    """out = sum_k g[k] * d basis_k / d(x, y, z) (x, y, z taken as independent)."""
    gx = 0.0
    gy = 0.0
    gz = 0.0
    if count > 1:
        gy -= _Y1 * g[1]
        gz += _Y1 * g[2]
        gx -= _Y1 * g[3]
    if count > 4:
        xx, yy, zz = x * x, y * y, z * z
        gx += _Y2_XY * y * g[4]
        gy += _Y2_XY * x * g[4]
        gy -= _Y2_XY * z * g[5]
        gz -= _Y2_XY * y * g[5]
        gx -= 2.0 * _Y2_Z2 * x * g[6]
        gy -= 2.0 * _Y2_Z2 * y * g[6]
        gz += 4.0 * _Y2_Z2 * z * g[6]
        gx -= _Y2_XY * z * g[7]
        gz -= _Y2_XY * x * g[7]
        gx += 2.0 * _Y2_XX_YY * x * g[8]
        gy -= 2.0 * _Y2_XX_YY * y * g[8]
        if count > 9:
            gx -= 6.0 * _Y3_A * x * y * g[9]
            gy -= _Y3_A * (3.0 * xx - 3.0 * yy) * g[9]
            gx += _Y3_B * y * z * g[10]
            gy += _Y3_B * x * z * g[10]
            gz += _Y3_B * x * y * g[10]
            gx += 2.0 * _Y3_C * x * y * g[11]
            gy -= _Y3_C * (4.0 * zz - xx - 3.0 * yy) * g[11]
            gz -= 8.0 * _Y3_C * y * z * g[11]
            gx -= 6.0 * _Y3_D * x * z * g[12]
            gy -= 6.0 * _Y3_D * y * z * g[12]
            gz += _Y3_D * (6.0 * zz - 3.0 * xx - 3.0 * yy) * g[12]
            gx -= _Y3_C * (4.0 * zz - 3.0 * xx - yy) * g[13]
            gy += 2.0 * _Y3_C * x * y * g[13]
            gz -= 8.0 * _Y3_C * x * z * g[13]
            gx += 2.0 * _Y3_E * x * z * g[14]
            gy -= 2.0 * _Y3_E * y * z * g[14]
            gz += _Y3_E * (xx - yy) * g[14]
            gx -= _Y3_A * (3.0 * xx - 3.0 * yy) * g[15]
            gy += 6.0 * _Y3_A * x * y * g[15]
    out[0] = gx
    out[1] = gy
    out[2] = gz


@njit(cache=True, parallel=True)
def sh_forward(coefficients, directions, count, out):
    """out[n, c] = max(sum_k Y_k(unit d_n) coefficients[n, k, c] + 0.5, 0)."""
    for n in prange(directions.shape[0]):
        basis = np.empty(16, dtype=np.float64)
        dx, dy, dz = directions[n, 0], directions[n, 1], directions[n, 2]
        norm = max(math.sqrt(dx * dx + dy * dy + dz * dz), _NORM_FLOOR)
        _basis(dx / norm, dy / norm, dz / norm, count, basis)
        for c in range(3):
            value = 0.5
            for k in range(count):
                value += basis[k] * coefficients[n, k, c]
            out[n, c] = value if value > 0.0 else 0.0


@njit(cache=True, parallel=True)
def sh_backward(coefficients, directions, count, grad_out, grad_coefficients, grad_directions):
    """Gradients of :func:`sh_forward` w.r.t. the first ``count`` coefficients and the directions."""
    for n in prange(directions.shape[0]):
        basis = np.empty(16, dtype=np.float64)
        grad_basis = np.zeros(16, dtype=np.float64)
        grad_unit = np.empty(3, dtype=np.float64)
        dx, dy, dz = directions[n, 0], directions[n, 1], directions[n, 2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        norm = max(length, _NORM_FLOOR)
        x, y, z = dx / norm, dy / norm, dz / norm
        _basis(x, y, z, count, basis)
        for c in range(3):
            value = 0.5
            for k in range(count):
                value += basis[k] * coefficients[n, k, c]
            g = grad_out[n, c] if value >= 0.0 else 0.0  # clamp_min passes the gradient at the bound
            for k in range(count):
                grad_coefficients[n, k, c] = basis[k] * g
                grad_basis[k] += coefficients[n, k, c] * g
        _basis_gradient(x, y, z, count, grad_basis, grad_unit)
        if length > _NORM_FLOOR:  # through u = d / |d|: (g - u (u . g)) / |d|
            along = x * grad_unit[0] + y * grad_unit[1] + z * grad_unit[2]
            grad_directions[n, 0] = (grad_unit[0] - x * along) / norm
            grad_directions[n, 1] = (grad_unit[1] - y * along) / norm
            grad_directions[n, 2] = (grad_unit[2] - z * along) / norm
        else:  # the floor is a constant: d / 1e-12
            grad_directions[n, 0] = grad_unit[0] / norm
            grad_directions[n, 1] = grad_unit[1] / norm
            grad_directions[n, 2] = grad_unit[2] / norm


class SHColors(torch.autograd.Function):
    """colours [N, 3] from coefficients [N, K, 3] (the first (degree + 1)^2 used) and directions [N, 3]."""

    @staticmethod
    def forward(ctx, coefficients: torch.Tensor, directions: torch.Tensor, degree: int) -> torch.Tensor:
        count = num_sh_bases(degree)
        coefficients_np = coefficients.detach().numpy()
        directions_np = directions.detach().contiguous().numpy()
        out = torch.empty(directions.shape[0], 3, dtype=coefficients.dtype)
        sh_forward(coefficients_np, directions_np, count, out.numpy())
        ctx.save_for_backward(coefficients, directions)
        ctx.count = count
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        coefficients, directions = ctx.saved_tensors
        grad_coefficients = torch.zeros_like(coefficients) if ctx.needs_input_grad[0] else None
        grad_directions = torch.empty(directions.shape, dtype=directions.dtype)
        scratch = grad_coefficients if grad_coefficients is not None else torch.empty_like(coefficients)
        sh_backward(coefficients.detach().numpy(), directions.detach().contiguous().numpy(), ctx.count,
                    grad_out.contiguous().numpy(), scratch.numpy(), grad_directions.numpy())
        return grad_coefficients, grad_directions if ctx.needs_input_grad[1] else None, None


def fused_sh_colors(degree: int, coefficients: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """:func:`.sh.evaluate_sh_colors` for CPU tensors with directions [N, 3], in Numba."""
    return SHColors.apply(coefficients, directions, int(degree))
