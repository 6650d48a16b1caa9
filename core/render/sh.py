"""Real spherical harmonics (degrees 0..3) to RGB, in the basis order 3DGS checkpoints use.

``colour = max(sum_k coefficient_k * Y_k(direction) + 0.5, 0)``, with ``direction`` the
unit vector from the camera centre to the Gaussian. Coefficient ``k`` of an ``[N, K, 3]``
tensor follows the usual ordering (l = 0; l = 1: m = -1, 0, 1; ...), with the sign
convention of 3DGS so trained PLY files load unchanged.
"""
from __future__ import annotations

import math

import torch

# Normalisation constants of the real spherical harmonics, written from the closed forms
# sqrt((2l + 1) / (4 pi) * (l - |m|)! / (l + |m|)!) (times sqrt(2) for m != 0) with the
# Legendre-polynomial factors folded in.
_Y00 = 0.5 * math.sqrt(1.0 / math.pi)
_Y1 = math.sqrt(3.0 / (4.0 * math.pi))
_Y2_XY = 0.5 * math.sqrt(15.0 / math.pi)
_Y2_Z2 = 0.25 * math.sqrt(5.0 / math.pi)
_Y2_XX_YY = 0.25 * math.sqrt(15.0 / math.pi)
_Y3_A = 0.25 * math.sqrt(35.0 / (2.0 * math.pi))
_Y3_B = 0.5 * math.sqrt(105.0 / math.pi)
_Y3_C = 0.25 * math.sqrt(21.0 / (2.0 * math.pi))
_Y3_D = 0.25 * math.sqrt(7.0 / math.pi)
_Y3_E = 0.25 * math.sqrt(105.0 / math.pi)


def num_sh_bases(degree: int) -> int:
    """Number of coefficients per channel for ``degree`` (1, 4, 9, 16)."""
    return (degree + 1) ** 2


def sh_basis(degree: int, directions: torch.Tensor) -> torch.Tensor:
    """Basis functions ``[..., (degree + 1)^2]`` at unit ``directions: [..., 3]``."""
    x, y, z = directions.unbind(-1)
    bases = [torch.full_like(x, _Y00)]
    if degree >= 1:
        bases += [-_Y1 * y, _Y1 * z, -_Y1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        bases += [
            _Y2_XY * x * y,
            -_Y2_XY * y * z,
            _Y2_Z2 * (2.0 * zz - xx - yy),
            -_Y2_XY * x * z,
            _Y2_XX_YY * (xx - yy),
        ]
    if degree >= 3:
        bases += [
            -_Y3_A * y * (3.0 * xx - yy),
            _Y3_B * x * y * z,
            -_Y3_C * y * (4.0 * zz - xx - yy),
            _Y3_D * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            -_Y3_C * x * (4.0 * zz - xx - yy),
            _Y3_E * z * (xx - yy),
            -_Y3_A * x * (xx - 3.0 * yy),
        ]
    return torch.stack(bases, dim=-1)


def evaluate_sh_colors(degree: int, coefficients: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """RGB colours from SH.

    coefficients: [N, K, 3] with K >= (degree + 1)^2 (extra bands are ignored)
    directions:   [..., N, 3] view directions (need not be unit length)
    returns:      [..., N, 3] colours, ``max(SH + 0.5, 0)``
    """
    count = num_sh_bases(degree)
    unit = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(degree, unit)  # [..., N, count]
    # a batched [1, count] x [count, 3] product per Gaussian: no [N, count, 3] temporary forward
    # (192 bytes a Gaussian at degree 3, kept for the backward too)
    values = torch.matmul(basis.unsqueeze(-2), coefficients[:, :count, :]).squeeze(-2)
    return torch.clamp_min(values + 0.5, 0.0)
