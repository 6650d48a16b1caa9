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

from .sh import _Y00, _Y1, _Y2_XX_YY, _Y2_XY, _Y2_Z2, _Y3_A, _Y3_B, _Y3_C, _Y3_D, _Y3_E, SHCoefficients, num_sh_bases

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


@njit(cache=True, inline="always")
def _coefficient(head, tail, n, k, c):
    """Coefficient k of Gaussian n: from ``head`` [N, H, 3] for k < H, else from ``tail``."""
    split = head.shape[1]
    return head[n, k, c] if k < split else tail[n, k - split, c]


@njit(cache=True, parallel=True)
def sh_forward(head, tail, directions, count, out):
    """out[n, c] = max(sum_k Y_k(unit d_n) coefficient[n, k, c] + 0.5, 0).

    The coefficients are the concatenation of ``head`` [N, H, 3] and ``tail`` [N, T, 3] along
    the basis axis (a trainer's ``sh_dc`` and ``sh_rest``; ``tail`` is empty for one tensor).
    """
    for n in prange(directions.shape[0]):
        basis = np.empty(16, dtype=np.float64)
        dx, dy, dz = directions[n, 0], directions[n, 1], directions[n, 2]
        norm = max(math.sqrt(dx * dx + dy * dy + dz * dz), _NORM_FLOOR)
        _basis(dx / norm, dy / norm, dz / norm, count, basis)
        for c in range(3):
            value = 0.5
            for k in range(count):
                value += basis[k] * _coefficient(head, tail, n, k, c)
            out[n, c] = value if value > 0.0 else 0.0


@njit(cache=True, parallel=True)
def sh_backward(head, tail, directions, count, grad_out, grad_head, grad_tail, grad_directions):
    """Gradients of :func:`sh_forward` w.r.t. the first ``count`` coefficients (into
    ``grad_head`` and ``grad_tail``, zero-filled by the caller) and the directions."""
    split = head.shape[1]
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
                value += basis[k] * _coefficient(head, tail, n, k, c)
            g = grad_out[n, c] if value >= 0.0 else 0.0  # clamp_min passes the gradient at the bound
            for k in range(count):
                if k < split:
                    grad_head[n, k, c] = basis[k] * g
                else:
                    grad_tail[n, k - split, c] = basis[k] * g
                grad_basis[k] += _coefficient(head, tail, n, k, c) * g
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
    """colours [N, 3] from coefficients ``head`` [N, H, 3] and ``tail`` [N, T, 3] (their
    concatenation; the first (degree + 1)^2 used) and directions [N, 3]."""

    @staticmethod
    def forward(ctx, head: torch.Tensor, tail: torch.Tensor, directions: torch.Tensor, degree: int) -> torch.Tensor:
        count = num_sh_bases(degree)
        directions = directions.detach().contiguous()
        out = torch.empty(directions.shape[0], 3, dtype=head.dtype)
        sh_forward(head.detach().numpy(), tail.detach().numpy(), directions.numpy(), count, out.numpy())
        ctx.save_for_backward(head, tail, directions)
        ctx.count = count
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        head, tail, directions = ctx.saved_tensors
        # the coefficient gradients are written in place, straight into tensors of their
        # parameters' shapes (the trainer's sh_dc and sh_rest gradients)
        grad_head = torch.zeros_like(head, memory_format=torch.contiguous_format)
        grad_tail = torch.zeros_like(tail, memory_format=torch.contiguous_format)
        grad_directions = torch.empty(directions.shape, dtype=directions.dtype)
        sh_backward(head.detach().numpy(), tail.detach().numpy(), directions.numpy(), ctx.count,
                    grad_out.contiguous().numpy(), grad_head.numpy(), grad_tail.numpy(), grad_directions.numpy())
        needs = ctx.needs_input_grad
        return (grad_head if needs[0] else None, grad_tail if needs[1] else None,
                grad_directions if needs[2] else None, None)


def fused_sh_colors(degree: int, coefficients: torch.Tensor | SHCoefficients, directions: torch.Tensor) -> torch.Tensor:
    """:func:`.sh.evaluate_sh_colors` for CPU tensors with directions [N, 3], in Numba.

    ``coefficients`` [N, K, 3], or :class:`~.sh.SHCoefficients` read in place (no concatenation).
    """
    if isinstance(coefficients, SHCoefficients):
        head, tail = coefficients.dc, coefficients.rest
    else:
        head, tail = coefficients, coefficients[:, :0]
    return SHColors.apply(head, tail, directions, int(degree))
