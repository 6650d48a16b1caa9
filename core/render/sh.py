"""Real spherical harmonics (degrees 0..3) to RGB, in the basis order 3DGS checkpoints use.

``colour = max(sum_k coefficient_k * Y_k(direction) + 0.5, 0)``, with ``direction`` the
unit vector from the camera centre to the Gaussian. Coefficient ``k`` of an ``[N, K, 3]``
tensor follows the usual ordering (l = 0; l = 1: m = -1, 0, 1; ...), with the sign
convention of 3DGS so trained PLY files load unchanged.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

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


@dataclass(frozen=True)
class SHCoefficients:
    """SH coefficients as the two tensors a trainer keeps them in: ``dc`` [N, 1, 3] (degree 0)
    and ``rest`` [N, K-1, 3] (the higher bands), the coefficients of ``torch.cat([dc, rest], 1)``.

    Hand it to :func:`~esgs.core.render.rasterization` as ``colors`` (with ``sh_degree``)
    instead of that concatenation: the ``cpu`` backend reads both in place and writes the two
    gradients directly, so no [N, K, 3] copy is made forward or backward (192 + 192 bytes a
    Gaussian at degree 3, ~150 MB at 400k Gaussians); the other backends concatenate once.
    """

    dc: torch.Tensor
    rest: torch.Tensor

    @property
    def shape(self) -> tuple[int, int, int]:
        """The shape of the concatenation, [N, K, 3]."""
        return (int(self.dc.shape[0]), int(self.dc.shape[1]) + int(self.rest.shape[1]), int(self.dc.shape[-1]))

    @property
    def dtype(self) -> torch.dtype:
        return self.dc.dtype

    @property
    def device(self) -> torch.device:
        return self.dc.device

    def cat(self) -> torch.Tensor:
        """[N, K, 3] all coefficients in one tensor (a copy)."""
        return torch.cat([self.dc, self.rest], dim=1)


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


def evaluate_sh_colors(degree: int, coefficients: torch.Tensor | SHCoefficients,
                       directions: torch.Tensor) -> torch.Tensor:
    """RGB colours from SH.

    coefficients: [N, K, 3] with K >= (degree + 1)^2 (extra bands are ignored), or
                  :class:`SHCoefficients` (concatenated here)
    directions:   [..., N, 3] view directions (need not be unit length)
    returns:      [..., N, 3] colours, ``max(SH + 0.5, 0)``
    """
    if isinstance(coefficients, SHCoefficients):
        coefficients = coefficients.cat()
    count = num_sh_bases(degree)
    unit = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(degree, unit)  # [..., N, count]
    # a batched [1, count] x [count, 3] product per Gaussian: no [N, count, 3] temporary forward
    # (192 bytes a Gaussian at degree 3, kept for the backward too)
    values = torch.matmul(basis.unsqueeze(-2), coefficients[:, :count, :]).squeeze(-2)
    return torch.clamp_min(values + 0.5, 0.0)
