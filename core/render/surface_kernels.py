"""The median surface's thickness along a prior normal in one Numba pass per pixel, forward and backward.

:func:`.surface.median_surface_thinness` in torch gathers each pixel's Gaussian, builds its
rotation matrix and reduces it: some thirty [pixels] temporaries per step, an index gather
forward and an accumulating scatter backward, for an image's worth of pixels (~130k at 480x270).
That was most of what the thin normal prior added to a CPU training step
(docs/training.md, "What ESGS adds to a step"). Here the forward computes each pixel's value
from the Gaussian's quaternion and scales directly, and the backward recomputes them per pixel
(in parallel) and then adds the gradients into the Gaussians' rows in one serial pass (a fixed
order, so the sums are the same on every run and thread count). Same maths as the torch expression, which stays
the reference and the path for other devices; the tests compare values and gradients with it
and with finite differences.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

_NORM_FLOOR = 1e-12  # as quaternion_to_matrix and the normal's normalisation: x / max(|x|, 1e-12)
_MEAN_VARIANCE_FLOOR = 1e-30  # as the torch expression's clamp of tr(Sigma) / 3


@njit(cache=True, inline="always")
def _rotation(w, x, y, z, out):
    """Rotation matrix (row-major 3x3 in ``out``) of the unit quaternion (w, x, y, z)."""
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    out[0, 0] = 1.0 - 2.0 * (yy + zz)
    out[0, 1] = 2.0 * (xy - wz)
    out[0, 2] = 2.0 * (xz + wy)
    out[1, 0] = 2.0 * (xy + wz)
    out[1, 1] = 1.0 - 2.0 * (xx + zz)
    out[1, 2] = 2.0 * (yz - wx)
    out[2, 0] = 2.0 * (xz - wy)
    out[2, 1] = 2.0 * (yz + wx)
    out[2, 2] = 1.0 - 2.0 * (xx + yy)


@njit(cache=True, inline="always")
def _pixel_terms(quats, scales, gaussian, normal, unit, rotation, along, variance):
    """Fill ``unit`` (normalised quaternion), ``rotation``, ``along`` (a_k . n) and ``variance``
    (s_k^2) of one pixel; return the quaternion's length before its floor."""
    length = math.sqrt(quats[gaussian, 0] ** 2 + quats[gaussian, 1] ** 2 + quats[gaussian, 2] ** 2
                       + quats[gaussian, 3] ** 2)
    divisor = max(length, _NORM_FLOOR)
    for c in range(4):
        unit[c] = quats[gaussian, c] / divisor
    _rotation(unit[0], unit[1], unit[2], unit[3], rotation)
    for k in range(3):
        along[k] = rotation[0, k] * normal[0] + rotation[1, k] * normal[1] + rotation[2, k] * normal[2]
        variance[k] = scales[gaussian, k] * scales[gaussian, k]
    return length


@njit(cache=True, inline="always")
def _world_normal(normals, row, col, camera_rotation, out):
    """Unit world normal of a pixel's camera-frame prior normal (R^T n, as the torch row product n R)."""
    for i in range(3):
        out[i] = (normals[row, col, 0] * camera_rotation[0, i] + normals[row, col, 1] * camera_rotation[1, i]
                  + normals[row, col, 2] * camera_rotation[2, i])
    length = max(math.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2]), _NORM_FLOOR)
    for i in range(3):
        out[i] /= length


@njit(cache=True, inline="always")
def _scratch():
    """Per-thread work arrays of one pixel: (unit quaternion, rotation, along, variance, world normal)."""
    return np.empty(4), np.empty((3, 3)), np.empty(3), np.empty(3), np.empty(3)


@njit(cache=True, parallel=True)
def thinness_forward(ids, quats, scales, normals, camera_rotation, out):
    """out[H, W] = thickness of pixel (row, col)'s Gaussian ``ids[row, col]`` along its normal (0 where id < 0)."""
    height, width = ids.shape
    for row in prange(height):
        unit, rotation, along, variance, normal = _scratch()
        for col in range(width):
            gaussian = ids[row, col]
            if gaussian < 0:
                out[row, col] = 0.0
                continue
            _world_normal(normals, row, col, camera_rotation, normal)
            _pixel_terms(quats, scales, gaussian, normal, unit, rotation, along, variance)
            mean_variance = max((variance[0] + variance[1] + variance[2]) / 3.0, _MEAN_VARIANCE_FLOOR)
            out[row, col] = (variance[0] * along[0] ** 2 + variance[1] * along[1] ** 2
                             + variance[2] * along[2] ** 2) / mean_variance


@njit(cache=True, parallel=True)
def _pixel_gradients(ids, quats, scales, normals, camera_rotation, grad_out, out):
    """out[H, W, 7]: each pixel's d loss / d (quaternion [4], scales [3]) of its own Gaussian (0 where none)."""
    height, width = ids.shape
    for row in prange(height):
        unit, rotation, along, variance, normal = _scratch()
        G = np.empty((3, 3))
        for col in range(width):
            gaussian = ids[row, col]
            g = grad_out[row, col]
            if gaussian < 0 or g == 0.0:
                for c in range(7):
                    out[row, col, c] = 0.0
                continue
            _world_normal(normals, row, col, camera_rotation, normal)
            length = _pixel_terms(quats, scales, gaussian, normal, unit, rotation, along, variance)
            total = variance[0] * along[0] ** 2 + variance[1] * along[1] ** 2 + variance[2] * along[2] ** 2
            mean_variance = (variance[0] + variance[1] + variance[2]) / 3.0
            floored = mean_variance <= _MEAN_VARIANCE_FLOOR
            divisor = _MEAN_VARIANCE_FLOOR if floored else mean_variance
            for k in range(3):
                # d thick / d variance_k: the numerator's term, less the mean's (none under the floor)
                d_variance = along[k] ** 2 / divisor
                if not floored:
                    d_variance -= total / (divisor * divisor) / 3.0
                out[row, col, 4 + k] = g * d_variance * 2.0 * scales[gaussian, k]
                # d thick / d along_k, then d along_k / d R[i, k] = n_i
                d_along = g * 2.0 * variance[k] * along[k] / divisor
                for i in range(3):
                    G[i, k] = d_along * normal[i]
            w, x, y, z = unit[0], unit[1], unit[2], unit[3]
            d_w = 2.0 * (-z * G[0, 1] + y * G[0, 2] + z * G[1, 0] - x * G[1, 2] - y * G[2, 0] + x * G[2, 1])
            d_x = 2.0 * (y * G[0, 1] + z * G[0, 2] + y * G[1, 0] - 2.0 * x * G[1, 1] - w * G[1, 2]
                         + z * G[2, 0] + w * G[2, 1] - 2.0 * x * G[2, 2])
            d_y = 2.0 * (-2.0 * y * G[0, 0] + x * G[0, 1] + w * G[0, 2] + x * G[1, 0] + z * G[1, 2]
                         - w * G[2, 0] + z * G[2, 1] - 2.0 * y * G[2, 2])
            d_z = 2.0 * (-2.0 * z * G[0, 0] - w * G[0, 1] + x * G[0, 2] + w * G[1, 0] - 2.0 * z * G[1, 1]
                         + y * G[1, 2] + x * G[2, 0] + y * G[2, 1])
            # through u = q / max(|q|, floor): (I - u u^T) / |q| above the floor, 1 / floor below
            if length > _NORM_FLOOR:
                radial = w * d_w + x * d_x + y * d_y + z * d_z
                out[row, col, 0] = (d_w - w * radial) / length
                out[row, col, 1] = (d_x - x * radial) / length
                out[row, col, 2] = (d_y - y * radial) / length
                out[row, col, 3] = (d_z - z * radial) / length
            else:
                out[row, col, 0] = d_w / _NORM_FLOOR
                out[row, col, 1] = d_x / _NORM_FLOOR
                out[row, col, 2] = d_y / _NORM_FLOOR
                out[row, col, 3] = d_z / _NORM_FLOOR


@njit(cache=True)
def _gather_gradients(ids, pixel_gradients, grad_quats, grad_scales):
    """Add every pixel's gradients into its Gaussian's rows, in raster order (serial: fixed sums)."""
    height, width = ids.shape
    for row in range(height):
        for col in range(width):
            gaussian = ids[row, col]
            if gaussian < 0:
                continue
            for c in range(4):
                grad_quats[gaussian, c] += pixel_gradients[row, col, c]
            for c in range(3):
                grad_scales[gaussian, c] += pixel_gradients[row, col, 4 + c]


def thinness_backward(ids, quats, scales, normals, camera_rotation, grad_out, grad_quats, grad_scales):
    """Add d loss / d quats and d loss / d scales of :func:`thinness_forward` into ``grad_quats``
    [N, 4] and ``grad_scales`` [N, 3] (zeroed by the caller): per pixel in parallel, then added
    into the Gaussians' rows in raster order."""
    pixel_gradients = np.empty(ids.shape + (7,), dtype=grad_quats.dtype)
    _pixel_gradients(ids, quats, scales, normals, camera_rotation, grad_out, pixel_gradients)
    _gather_gradients(ids, pixel_gradients, grad_quats, grad_scales)


class Thinness(torch.autograd.Function):
    """thickness [H, W] from ids [H, W] (int, -1 = none), quats [N, 4], scales [N, 3], camera-frame
    normals [H, W, 3] and the world-to-camera rotation [3, 3]; gradients reach quats and scales."""

    @staticmethod
    def forward(ctx, ids: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, normals: torch.Tensor,
                camera_rotation: torch.Tensor) -> torch.Tensor:
        # saved as tensors (not arrays), so autograd notices an in-place change before the backward
        inputs = (ids.contiguous(), quats.detach().contiguous(), scales.detach().contiguous(),
                  normals.detach().to(quats.dtype).contiguous(), camera_rotation.detach().to(quats.dtype).contiguous())
        out = torch.empty(ids.shape, dtype=quats.dtype)
        thinness_forward(*(tensor.numpy() for tensor in inputs), out.numpy())
        ctx.save_for_backward(*inputs)
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        inputs = ctx.saved_tensors
        grad_quats = torch.zeros(inputs[1].shape, dtype=grad_out.dtype)
        grad_scales = torch.zeros(inputs[2].shape, dtype=grad_out.dtype)
        thinness_backward(*(tensor.numpy() for tensor in inputs), grad_out.contiguous().numpy(), grad_quats.numpy(),
                          grad_scales.numpy())
        return (None, grad_quats if ctx.needs_input_grad[1] else None,
                grad_scales if ctx.needs_input_grad[2] else None, None, None)


def fused_thinness(median_ids: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, viewmat: torch.Tensor,
                   normals: torch.Tensor) -> torch.Tensor:
    """:func:`.surface.median_surface_thinness`'s values [H, W] for CPU tensors, in Numba (0 where no Gaussian)."""
    return Thinness.apply(median_ids, quats, scales, normals, viewmat[:3, :3])
