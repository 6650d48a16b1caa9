"""Vectorised torch projection of 3D Gaussians to screen-space splats.

The readable statement of the CPU backend's projection rule: the Numba kernels in
:mod:`.projection_kernels` implement the same maths with a hand-written backward, and a
test keeps the two equal (values and autograd gradients). The CUDA mapping uses it for
the camera-frame normals. Culled Gaussians get finite placeholder values so that no NaN or inf can leak into
gradients through ``torch.where`` (0 * inf = NaN).
"""
from __future__ import annotations

import torch

from . import constants as K


def quaternion_to_matrix(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), any non-zero length -> [N, 3, 3] rotation matrices."""
    unit = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = unit.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return torch.stack([
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    ], dim=-1).reshape(quats.shape[0], 3, 3)


def project_points(points: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, *,
                   near_plane: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pinhole projection of [N, 3] world points into one camera (viewmat [4, 4] world-to-camera,
    OpenCV axes; K [3, 3]): ``(u [N], v [N], z [N], in_front [N] bool)`` in pixels and camera z.

    Points at or behind ``near_plane`` get ``in_front`` False, z = 1 and finite (meaningless)
    pixels, so no inf or NaN leaks into later arithmetic (a caller may divide by z).
    """
    viewmat, K = viewmat.to(points), K.to(points)
    camera = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = camera[:, 2]
    in_front = z > near_plane
    safe_z = torch.where(in_front, z, torch.ones_like(z))
    u = K[0, 0] * camera[:, 0] / safe_z + K[0, 2]
    v = K[1, 1] * camera[:, 1] / safe_z + K[1, 2]
    return u, v, safe_z, in_front


def project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, *, near_plane, far_plane,
                      antialiased, eps2d, need_normals):
    """Project N Gaussians into C cameras.

    Returns a dict of tensors:
      means2d [C, N, 2] pixel coordinates; conics [C, N, 3] (a, b, c) of the inverse
      dilated 2D covariance [[a, b], [b, c]]; opacities [C, N] (with the antialiasing
      compensation); depths [C, N] camera z; normals [C, N, 3] or None;
      and, without grad, cov_diagonal [C, N, 2] of the dilated covariance and valid [C, N].
    """
    rotation = quaternion_to_matrix(quats)  # [N, 3, 3]
    view_rotation = viewmats[:, :3, :3]  # [C, 3, 3]
    view_translation = viewmats[:, :3, 3]  # [C, 3]
    points = torch.einsum("cij,nj->cni", view_rotation, means) + view_translation[:, None, :]
    x, y, z = points.unbind(-1)
    valid = (z > near_plane) & (z < far_plane)
    depth_safe = torch.where(valid, z, torch.ones_like(z))
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    inv_depth = 1.0 / depth_safe
    slope_x, slope_y = x * inv_depth, y * inv_depth
    means2d = torch.stack([fx * slope_x + cx, fy * slope_y + cy], dim=-1)
    clamped_x = torch.minimum(torch.maximum(slope_x, (-K.JACOBIAN_MARGIN * width - cx) / fx),
                              ((1 + K.JACOBIAN_MARGIN) * width - cx) / fx)
    clamped_y = torch.minimum(torch.maximum(slope_y, (-K.JACOBIAN_MARGIN * height - cy) / fy),
                              ((1 + K.JACOBIAN_MARGIN) * height - cy) / fy)
    # Rows of J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]] applied to the camera-frame
    # covariance W R S S R^T W^T, computed as (J W R S)(J W R S)^T.
    camera_axes = torch.einsum("cij,njk->cnik", view_rotation, rotation)  # [C, N, 3, 3]
    scaled = camera_axes * scales[None, :, None, :]
    row_x = (fx * inv_depth)[..., None] * (scaled[..., 0, :] - clamped_x[..., None] * scaled[..., 2, :])
    row_y = (fy * inv_depth)[..., None] * (scaled[..., 1, :] - clamped_y[..., None] * scaled[..., 2, :])
    cov_xx = (row_x * row_x).sum(-1)
    cov_xy = (row_x * row_y).sum(-1)
    cov_yy = (row_y * row_y).sum(-1)
    dilation = eps2d if antialiased else K.CLASSIC_DILATION
    dil_xx, dil_yy = cov_xx + dilation, cov_yy + dilation
    det = dil_xx * dil_yy - cov_xy * cov_xy
    effective_opacity = opacities.expand_as(z)
    if antialiased:
        det_before = (cov_xx * cov_yy - cov_xy * cov_xy).clamp_min(0.0)
        ratio = det_before / det.clamp_min(1e-30)
        # sqrt has an infinite slope at 0 (flat or point Gaussians): keep it out of autograd.
        positive = ratio > 0
        compensation = torch.where(positive, torch.sqrt(torch.where(positive, ratio, torch.ones_like(ratio))),
                                   torch.zeros_like(ratio))
        effective_opacity = effective_opacity * compensation
    valid = valid & (det > 0) & torch.isfinite(det)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([dil_yy / det_safe, -cov_xy / det_safe, dil_xx / det_safe], dim=-1)
    normals = None
    if need_normals:
        shortest = torch.argmin(scales, dim=-1)  # [N]
        index = shortest[None, :, None, None].expand(camera_axes.shape[0], -1, 3, 1)
        normals = torch.gather(camera_axes, 3, index)[..., 0]  # [C, N, 3]
        away = (normals * points).sum(-1, keepdim=True) > 0
        normals = torch.where(away, -normals, normals)
    return {
        "means2d": means2d, "conics": conics, "opacities": effective_opacity, "depths": z,
        "normals": normals, "valid": valid.detach(),
        "cov_diagonal": torch.stack([dil_xx, dil_yy], dim=-1).detach(),
    }
