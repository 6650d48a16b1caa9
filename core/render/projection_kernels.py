"""Numba projection of 3D Gaussians to screen space, forward and hand-written backward.

Same rule as :mod:`.projection` (the vectorised torch version, kept as the readable
statement of the maths and used by the CUDA mapping for normals): per camera c and
Gaussian n, camera point p = W m + t, centre (fx p_x / p_z + cx, fy p_y / p_z + cy),
covariance J W R S S R^T W^T J^T with the Jacobian at the clamped image-plane position,
dilation, antialiasing opacity factor, conic = inverse dilated covariance, and the
shortest axis of W R flipped towards the camera. The CPU backend passes float64 arrays
whatever the input dtype (one compiled version; the arithmetic is float64 in any case). The backward recomputes the forward per Gaussian and applies the chain
rule by hand; per-Gaussian gradients are summed over cameras in camera order, so the
result is deterministic.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _rotation(qw, qx, qy, qz):
    norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if norm < 1e-12:
        norm = 1e-12
    w = qw / norm
    x = qx / norm
    y = qy / norm
    z = qz / norm
    rot = np.empty((3, 3))
    rot[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    rot[0, 1] = 2.0 * (x * y - w * z)
    rot[0, 2] = 2.0 * (x * z + w * y)
    rot[1, 0] = 2.0 * (x * y + w * z)
    rot[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    rot[1, 2] = 2.0 * (y * z - w * x)
    rot[2, 0] = 2.0 * (x * z - w * y)
    rot[2, 1] = 2.0 * (y * z + w * x)
    rot[2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return rot, w, x, y, z, norm


@njit(cache=True, inline="always")
def _shortest_axis(scales, n):
    best = 0
    for j in range(1, 3):
        if scales[n, j] < scales[n, best]:
            best = j
    return best


@njit(cache=True, inline="always")
def _intrinsics(Ks, cam):
    """fx, fy, cx, cy of camera ``cam`` (Ks [C, 3, 3]) in float64."""
    return np.float64(Ks[cam, 0, 0]), np.float64(Ks[cam, 1, 1]), np.float64(Ks[cam, 0, 2]), np.float64(Ks[cam, 1, 2])


@njit(cache=True, inline="always")
def _camera_point(view, means, n):
    """Mean ``n`` (means [N, 3]) in the frame of the world-to-camera ``view`` [4, 4], float64 [3]."""
    p = np.empty(3)
    for i in range(3):
        p[i] = (np.float64(view[i, 0]) * means[n, 0] + np.float64(view[i, 1]) * means[n, 1]
                + np.float64(view[i, 2]) * means[n, 2] + np.float64(view[i, 3]))
    return p


@njit(cache=True, parallel=True)
def project_forward(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane,
                    dilation, antialiased, margin, need_normals,
                    out_means2d, out_conics, out_opacities, out_depths, out_normals, out_valid, out_cov_diagonal):
    """Outputs [C, N, ...]: means2d (2), conics (3: a, b, c of [[a, b], [b, c]]), opacities,
    depths, normals (3, only when need_normals), valid (bool), cov_diagonal (2, dilated)."""
    cameras = viewmats.shape[0]
    for n in prange(means.shape[0]):
        rot, _, _, _, _, _ = _rotation(np.float64(quats[n, 0]), np.float64(quats[n, 1]),
                                       np.float64(quats[n, 2]), np.float64(quats[n, 3]))
        shortest = _shortest_axis(scales, n)
        for cam in range(cameras):
            view = viewmats[cam]
            fx, fy, cx, cy = _intrinsics(Ks, cam)
            p = _camera_point(view, means, n)
            valid = p[2] > near_plane and p[2] < far_plane
            depth = p[2] if valid else 1.0
            inv_depth = 1.0 / depth
            slope_x = p[0] * inv_depth
            slope_y = p[1] * inv_depth
            out_means2d[cam, n, 0] = fx * slope_x + cx
            out_means2d[cam, n, 1] = fy * slope_y + cy
            out_depths[cam, n] = p[2]
            clamped_x = min(max(slope_x, (-margin * width - cx) / fx), ((1.0 + margin) * width - cx) / fx)
            clamped_y = min(max(slope_y, (-margin * height - cy) / fy), ((1.0 + margin) * height - cy) / fy)
            # axes = W R (columns: the Gaussian's axes in the camera frame)
            axes = np.empty((3, 3))
            for i in range(3):
                for j in range(3):
                    axes[i, j] = (np.float64(view[i, 0]) * rot[0, j] + np.float64(view[i, 1]) * rot[1, j]
                                  + np.float64(view[i, 2]) * rot[2, j])
            cov_xx = 0.0
            cov_xy = 0.0
            cov_yy = 0.0
            for j in range(3):
                s = np.float64(scales[n, j])
                row_x = fx * inv_depth * (axes[0, j] - clamped_x * axes[2, j]) * s
                row_y = fy * inv_depth * (axes[1, j] - clamped_y * axes[2, j]) * s
                cov_xx += row_x * row_x
                cov_xy += row_x * row_y
                cov_yy += row_y * row_y
            dil_xx = cov_xx + dilation
            dil_yy = cov_yy + dilation
            det = dil_xx * dil_yy - cov_xy * cov_xy
            opacity = np.float64(opacities[n])
            if antialiased:
                det_before = max(cov_xx * cov_yy - cov_xy * cov_xy, 0.0)
                ratio = det_before / max(det, 1e-30)
                opacity = opacity * math.sqrt(ratio) if ratio > 0 else 0.0
            valid = valid and det > 0 and math.isfinite(det)
            det_safe = det if valid else 1.0
            out_conics[cam, n, 0] = dil_yy / det_safe
            out_conics[cam, n, 1] = -cov_xy / det_safe
            out_conics[cam, n, 2] = dil_xx / det_safe
            out_opacities[cam, n] = opacity
            out_valid[cam, n] = valid
            out_cov_diagonal[cam, n, 0] = dil_xx
            out_cov_diagonal[cam, n, 1] = dil_yy
            if need_normals:
                sign = 1.0
                if axes[0, shortest] * p[0] + axes[1, shortest] * p[1] + axes[2, shortest] * p[2] > 0:
                    sign = -1.0
                for i in range(3):
                    out_normals[cam, n, i] = sign * axes[i, shortest]


@njit(cache=True, parallel=True)
def project_backward(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane,
                     dilation, antialiased, margin, need_normals,
                     grad_means2d, grad_conics, grad_opacities, grad_depths, grad_normals,
                     out_means, out_quats, out_scales, out_opacities):
    """Gradients w.r.t. means [N, 3], quats [N, 4], scales [N, 3], opacities [N] (written,
    not accumulated) from the gradients of the forward's outputs ([C, N, ...])."""
    cameras = viewmats.shape[0]
    for n in prange(means.shape[0]):
        rot, w, x, y, z, norm = _rotation(np.float64(quats[n, 0]), np.float64(quats[n, 1]),
                                          np.float64(quats[n, 2]), np.float64(quats[n, 3]))
        shortest = _shortest_axis(scales, n)
        g_mean = np.zeros(3)
        g_rot = np.zeros((3, 3))
        g_scale = np.zeros(3)
        g_opacity = 0.0
        for cam in range(cameras):
            view = viewmats[cam]
            fx, fy, cx, cy = _intrinsics(Ks, cam)
            p = _camera_point(view, means, n)
            in_range = p[2] > near_plane and p[2] < far_plane
            g_p = np.zeros(3)
            g_p[2] = np.float64(grad_depths[cam, n])
            if in_range:
                inv_depth = 1.0 / p[2]
                slope_x = p[0] * inv_depth
                slope_y = p[1] * inv_depth
                low_x = (-margin * width - cx) / fx
                high_x = ((1.0 + margin) * width - cx) / fx
                low_y = (-margin * height - cy) / fy
                high_y = ((1.0 + margin) * height - cy) / fy
                clamped_x = min(max(slope_x, low_x), high_x)
                clamped_y = min(max(slope_y, low_y), high_y)
                axes = np.empty((3, 3))
                for i in range(3):
                    for j in range(3):
                        axes[i, j] = (np.float64(view[i, 0]) * rot[0, j] + np.float64(view[i, 1]) * rot[1, j]
                                      + np.float64(view[i, 2]) * rot[2, j])
                rows_x = np.empty(3)
                rows_y = np.empty(3)
                cov_xx = 0.0
                cov_xy = 0.0
                cov_yy = 0.0
                for j in range(3):
                    s = np.float64(scales[n, j])
                    rows_x[j] = fx * inv_depth * (axes[0, j] - clamped_x * axes[2, j]) * s
                    rows_y[j] = fy * inv_depth * (axes[1, j] - clamped_y * axes[2, j]) * s
                    cov_xx += rows_x[j] * rows_x[j]
                    cov_xy += rows_x[j] * rows_y[j]
                    cov_yy += rows_y[j] * rows_y[j]
                dil_xx = cov_xx + dilation
                dil_yy = cov_yy + dilation
                det = dil_xx * dil_yy - cov_xy * cov_xy
                valid = det > 0 and math.isfinite(det)
                g_slope_x = fx * np.float64(grad_means2d[cam, n, 0])
                g_slope_y = fy * np.float64(grad_means2d[cam, n, 1])
                g_axes = np.zeros((3, 3))
                g_inv_depth = 0.0
                if valid:
                    # conic = (dil_yy, -cov_xy, dil_xx) / det
                    inv_det = 1.0 / det
                    g_a = np.float64(grad_conics[cam, n, 0])
                    g_b = np.float64(grad_conics[cam, n, 1])
                    g_c = np.float64(grad_conics[cam, n, 2])
                    g_det = -(g_a * dil_yy - g_b * cov_xy + g_c * dil_xx) * inv_det * inv_det
                    g_dil_xx = g_c * inv_det + g_det * dil_yy
                    g_dil_yy = g_a * inv_det + g_det * dil_xx
                    g_cov_xy = -g_b * inv_det - 2.0 * g_det * cov_xy
                    opacity = np.float64(opacities[n])
                    g_effective = np.float64(grad_opacities[cam, n])
                    g_cov_xx = g_dil_xx
                    g_cov_yy = g_dil_yy
                    if antialiased:
                        det_before = cov_xx * cov_yy - cov_xy * cov_xy
                        ratio = max(det_before, 0.0) / det
                        if ratio > 0:
                            compensation = math.sqrt(ratio)
                            g_opacity += g_effective * compensation
                            g_ratio = g_effective * opacity * 0.5 / compensation
                            g_before = g_ratio * inv_det
                            g_det_after = -g_ratio * ratio * inv_det
                            g_cov_xx += g_before * cov_yy + g_det_after * dil_yy
                            g_cov_yy += g_before * cov_xx + g_det_after * dil_xx
                            g_cov_xy += -2.0 * cov_xy * (g_before + g_det_after)
                    else:
                        g_opacity += g_effective
                    g_clamped_x = 0.0
                    g_clamped_y = 0.0
                    for j in range(3):
                        s = np.float64(scales[n, j])
                        g_row_x = 2.0 * g_cov_xx * rows_x[j] + g_cov_xy * rows_y[j]
                        g_row_y = 2.0 * g_cov_yy * rows_y[j] + g_cov_xy * rows_x[j]
                        # rows_x[j] = fx inv_depth (axes[0, j] - clamped_x axes[2, j]) s
                        base_x = axes[0, j] - clamped_x * axes[2, j]
                        base_y = axes[1, j] - clamped_y * axes[2, j]
                        g_inv_depth += g_row_x * fx * base_x * s + g_row_y * fy * base_y * s
                        g_scale[j] += g_row_x * fx * inv_depth * base_x + g_row_y * fy * inv_depth * base_y
                        g_axes[0, j] += g_row_x * fx * inv_depth * s
                        g_axes[1, j] += g_row_y * fy * inv_depth * s
                        g_axes[2, j] -= (g_row_x * fx * clamped_x + g_row_y * fy * clamped_y) * inv_depth * s
                        g_clamped_x -= g_row_x * fx * inv_depth * axes[2, j] * s
                        g_clamped_y -= g_row_y * fy * inv_depth * axes[2, j] * s
                    if low_x < slope_x < high_x:
                        g_slope_x += g_clamped_x
                    if low_y < slope_y < high_y:
                        g_slope_y += g_clamped_y
                if need_normals:
                    sign = 1.0
                    if axes[0, shortest] * p[0] + axes[1, shortest] * p[1] + axes[2, shortest] * p[2] > 0:
                        sign = -1.0
                    for i in range(3):
                        g_axes[i, shortest] += sign * np.float64(grad_normals[cam, n, i])
                # slope = p_xy * inv_depth, inv_depth = 1 / p_z
                g_inv_depth += g_slope_x * p[0] + g_slope_y * p[1]
                g_p[0] += g_slope_x * inv_depth
                g_p[1] += g_slope_y * inv_depth
                g_p[2] -= g_inv_depth * inv_depth * inv_depth
                # axes = W R  ->  g_R += W^T g_axes
                for i in range(3):
                    for j in range(3):
                        g_rot[i, j] += (np.float64(view[0, i]) * g_axes[0, j] + np.float64(view[1, i]) * g_axes[1, j]
                                        + np.float64(view[2, i]) * g_axes[2, j])
            elif need_normals:
                # Culled by depth: normals still come out (composited nowhere), keep them exact.
                axes_column = np.empty(3)
                for i in range(3):
                    axes_column[i] = (np.float64(view[i, 0]) * rot[0, shortest] + np.float64(view[i, 1]) * rot[1, shortest]
                                      + np.float64(view[i, 2]) * rot[2, shortest])
                sign = -1.0 if axes_column[0] * p[0] + axes_column[1] * p[1] + axes_column[2] * p[2] > 0 else 1.0
                for i in range(3):
                    for a in range(3):
                        g_rot[i, shortest] += np.float64(view[a, i]) * sign * np.float64(grad_normals[cam, n, a])
            # p = W m + t
            for i in range(3):
                g_mean[i] += (np.float64(view[0, i]) * g_p[0] + np.float64(view[1, i]) * g_p[1]
                              + np.float64(view[2, i]) * g_p[2])
        # Rotation matrix entries -> unit quaternion -> raw quaternion.
        g_w = 2.0 * (-z * g_rot[0, 1] + y * g_rot[0, 2] + z * g_rot[1, 0] - x * g_rot[1, 2] - y * g_rot[2, 0]
                     + x * g_rot[2, 1])
        g_x = 2.0 * (y * g_rot[0, 1] + z * g_rot[0, 2] + y * g_rot[1, 0] - 2.0 * x * g_rot[1, 1] - w * g_rot[1, 2]
                     + z * g_rot[2, 0] + w * g_rot[2, 1] - 2.0 * x * g_rot[2, 2])
        g_y = 2.0 * (-2.0 * y * g_rot[0, 0] + x * g_rot[0, 1] + w * g_rot[0, 2] + x * g_rot[1, 0] + z * g_rot[1, 2]
                     - w * g_rot[2, 0] + z * g_rot[2, 1] - 2.0 * y * g_rot[2, 2])
        g_z = 2.0 * (-2.0 * z * g_rot[0, 0] - w * g_rot[0, 1] + x * g_rot[0, 2] + w * g_rot[1, 0]
                     - 2.0 * z * g_rot[1, 1] + y * g_rot[1, 2] + x * g_rot[2, 0] + y * g_rot[2, 1])
        radial = w * g_w + x * g_x + y * g_y + z * g_z
        out_quats[n, 0] = (g_w - w * radial) / norm
        out_quats[n, 1] = (g_x - x * radial) / norm
        out_quats[n, 2] = (g_y - y * radial) / norm
        out_quats[n, 3] = (g_z - z * radial) / norm
        for i in range(3):
            out_means[n, i] = g_mean[i]
            out_scales[n, i] = g_scale[i]
        out_opacities[n] = g_opacity
