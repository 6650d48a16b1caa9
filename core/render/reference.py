"""Dense pure-torch rasterizer: slow, simple, trusted.

It exists to check the fast backends. It shares no projection or compositing code with
them (only the cut-off numbers in :mod:`.constants` and the SH basis), so a mistake in one
shows up as a mismatch. Every pixel evaluates every Gaussian in front of the camera,
sorted by depth; compositing is a cumulative product and gradients come from autograd.
Pixels are processed in chunks under activation checkpointing, so memory stays at one
chunk's worth (``[pixels_per_chunk, N]`` tensors) in the forward and the backward pass.
"""
from __future__ import annotations


import torch
from torch.utils.checkpoint import checkpoint

from . import constants as K


def _rotation_matrices(quaternions: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), any length -> [N, 3, 3] rotation matrices."""
    w, x, y, z = (quaternions / quaternions.norm(dim=-1, keepdim=True)).unbind(-1)
    # Rotation as the product of the left- and right-multiplication matrices of q,
    # restricted to the vector part: R v = q v q*.
    rows = [
        torch.stack([w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z], -1),
    ]
    return torch.stack(rows, dim=-2)


def _camera_splats(means, quats, scales, opacities, viewmat, K_matrix, width, height,
                   near_plane, far_plane, antialiased, eps2d):
    """Per-camera screen-space Gaussians for one camera (no culling beyond near/far)."""
    rotation_world = viewmat[:3, :3]
    translation = viewmat[:3, 3]
    points = means @ rotation_world.T + translation  # [N, 3]
    depth = points[:, 2]
    in_range = (depth > near_plane) & (depth < far_plane)
    safe_depth = torch.where(in_range, depth, torch.ones_like(depth))
    fx, fy, cx, cy = K_matrix[0, 0], K_matrix[1, 1], K_matrix[0, 2], K_matrix[1, 2]
    u = fx * points[:, 0] / safe_depth + cx
    v = fy * points[:, 1] / safe_depth + cy
    # Jacobian of the pinhole projection at a position clamped to the widened image.
    slope_x = torch.clamp(points[:, 0] / safe_depth,
                          (-K.JACOBIAN_MARGIN * width - cx) / fx,
                          ((1 + K.JACOBIAN_MARGIN) * width - cx) / fx)
    slope_y = torch.clamp(points[:, 1] / safe_depth,
                          (-K.JACOBIAN_MARGIN * height - cy) / fy,
                          ((1 + K.JACOBIAN_MARGIN) * height - cy) / fy)
    zeros = torch.zeros_like(safe_depth)
    jacobian = torch.stack([
        torch.stack([fx / safe_depth, zeros, -fx * slope_x / safe_depth], -1),
        torch.stack([zeros, fy / safe_depth, -fy * slope_y / safe_depth], -1),
    ], dim=-2)  # [N, 2, 3]
    # Square root of the world covariance mapped straight to the screen: M M^T = J W R S S R^T W^T J^T.
    factor = jacobian @ rotation_world @ _rotation_matrices(quats) * scales[:, None, :]
    cov = factor @ factor.transpose(-1, -2)  # [N, 2, 2]
    dilation = eps2d if antialiased else K.CLASSIC_DILATION
    cov_dilated = cov + dilation * torch.eye(2, dtype=cov.dtype)
    opacity = opacities
    if antialiased:
        det_before = torch.linalg.det(cov).clamp_min(0.0)
        det_after = torch.linalg.det(cov_dilated)
        ratio = det_before / det_after
        nonzero = ratio > 0  # sqrt'(0) is infinite: degenerate Gaussians get no gradient through it
        opacity = opacities * torch.where(nonzero, torch.sqrt(torch.where(nonzero, ratio, torch.ones_like(ratio))),
                                          torch.zeros_like(ratio))
    precision = torch.linalg.inv(cov_dilated)
    return {
        "points": points, "depth": depth, "in_range": in_range,
        "means2d": torch.stack([u, v], -1), "cov": cov_dilated, "precision": precision,
        "opacity": opacity, "rotation_world": rotation_world,
    }


def _composite_chunk(pixel_xy, means2d, precision, opacity, features):
    """Composite depth-sorted Gaussians at pixels.

    pixel_xy: [P, 2]; means2d: [M, 2]; precision: [M, 2, 2]; opacity: [M]; features: [M, F]
    returns features [P, F], the weight sum [P], transmittance [P] and the position (in the
    depth order) of the Gaussian that takes the transmittance to one half or below [P]
    (-1 where it stays above).
    """
    offset = pixel_xy[:, None, :] - means2d[None, :, :]  # [P, M, 2]
    mahalanobis = torch.einsum("pmi,mij,pmj->pm", offset, precision, offset)
    raw = opacity[None, :] * torch.exp(-0.5 * mahalanobis)
    alpha = torch.clamp(raw, max=K.ALPHA_MAX)
    alpha = torch.where(alpha >= K.ALPHA_MIN, alpha, torch.zeros_like(alpha))
    survive_inclusive = torch.cumprod(1.0 - alpha, dim=1)
    included = survive_inclusive >= K.TRANSMITTANCE_MIN
    survive_before = torch.cat([torch.ones_like(survive_inclusive[:, :1]), survive_inclusive[:, :-1]], dim=1)
    weights = torch.where(included, alpha * survive_before, torch.zeros_like(alpha))
    transmittance = torch.prod(torch.where(included, 1.0 - alpha, torch.ones_like(alpha)), dim=1)
    with torch.no_grad():
        crosses = included & (survive_before > 0.5) & (survive_inclusive <= 0.5)
        crossing = torch.where(crosses.any(dim=1), crosses.to(torch.int8).argmax(dim=1), -1)
    return weights @ features, weights.sum(dim=1), transmittance, crossing


def rasterize_reference(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *,
                        near_plane, far_plane, sh_degree, backgrounds, render_depth, render_normals,
                        extra, antialiased, eps2d, pixels_per_chunk: int | None = None,
                        evaluate_colors=None):
    """See :func:`esgs.core.render.rasterization`; returns (render, alpha, meta)."""
    cameras = viewmats.shape[0]
    count = means.shape[0]
    dtype = means.dtype
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dtype), torch.arange(width, dtype=dtype), indexing="ij")
    pixel_xy = torch.stack([xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5], -1)
    renders, alphas, all_radii, median_ids = [], [], [], []
    splats = [_camera_splats(means, quats, scales, opacities, viewmats[cam], Ks[cam], width, height,
                             near_plane, far_plane, antialiased, eps2d) for cam in range(cameras)]
    # One tensor for all cameras, used downstream, so that its .grad is the screen-space gradient.
    means2d = torch.stack([splat["means2d"] for splat in splats])
    for cam in range(cameras):
        splat = splats[cam]
        splat["means2d"] = means2d[cam]
        channels = [evaluate_colors(cam)]
        if render_depth:
            channels.append(splat["depth"][:, None])
        if render_normals:
            axes = splat["rotation_world"] @ _rotation_matrices(quats)  # columns = axes in camera frame
            shortest = torch.argmin(scales, dim=-1)
            normal = torch.gather(axes, 2, shortest[:, None, None].expand(count, 3, 1))[..., 0]
            facing = (normal * splat["points"]).sum(-1, keepdim=True) > 0
            channels.append(torch.where(facing, -normal, normal))
        if extra is not None:
            channels.append(extra)
        features = torch.cat(channels, dim=-1)
        # The visible set: in front of the camera and able to reach alpha 1/255 somewhere.
        visible = splat["in_range"] & (splat["opacity"] >= K.ALPHA_MIN)
        index = torch.nonzero(visible).squeeze(-1)
        order = index[torch.argsort(splat["depth"][index], stable=True)]
        args = (splat["means2d"][order], splat["precision"][order], splat["opacity"][order], features[order])
        feature_count = features.shape[1]
        pixels = width * height
        if pixels_per_chunk is None:
            per_pixel_bytes = max(1, order.numel()) * 8 * 12
            pixels_per_chunk_now = int(max(64, min(pixels, 128 * 2**20 // per_pixel_bytes)))
        else:
            pixels_per_chunk_now = pixels_per_chunk
        out_features, out_weight, out_transmittance, out_crossing = [], [], [], []
        for start in range(0, pixels, pixels_per_chunk_now):
            chunk = pixel_xy[start:start + pixels_per_chunk_now]
            if order.numel() == 0:
                out_features.append(torch.zeros(chunk.shape[0], feature_count, dtype=dtype))
                out_weight.append(torch.zeros(chunk.shape[0], dtype=dtype))
                out_transmittance.append(torch.ones(chunk.shape[0], dtype=dtype))
                out_crossing.append(torch.full((chunk.shape[0],), -1, dtype=torch.long))
                continue
            if torch.is_grad_enabled():
                result = checkpoint(_composite_chunk, chunk, *args, use_reentrant=False)
            else:
                result = _composite_chunk(chunk, *args)
            out_features.append(result[0])
            out_weight.append(result[1])
            out_transmittance.append(result[2])
            out_crossing.append(result[3])
        composite = torch.cat(out_features).reshape(height, width, feature_count)
        weight_sum = torch.cat(out_weight).reshape(height, width, 1)
        alpha = 1.0 - torch.cat(out_transmittance).reshape(height, width, 1)
        crossing = torch.cat(out_crossing).reshape(height, width)
        median_ids.append(torch.where(crossing >= 0, order[crossing.clamp_min(0)] if order.numel() else crossing,
                                      -1))
        color_dims = channels[0].shape[1]
        pieces = [composite[..., :color_dims]]
        if backgrounds is not None:
            pieces[0] = pieces[0] + (1.0 - alpha) * backgrounds[cam]
        cursor = color_dims
        if render_depth:
            depth_sum = composite[..., cursor:cursor + 1]
            has = weight_sum > 0
            pieces.append(torch.where(has, depth_sum / torch.where(has, weight_sum, torch.ones_like(weight_sum)),
                                      torch.zeros_like(depth_sum)))
            cursor += 1
        pieces.append(composite[..., cursor:])
        renders.append(torch.cat(pieces, dim=-1))
        alphas.append(alpha)
        # Radii for the meta only (rendering above never uses them): the half extent of the
        # box where opacity * exp(-q / 2) can reach 1/255, rounded up; 0 when it cannot.
        with torch.no_grad():
            level = 2.0 * (torch.log(splat["opacity"].clamp_min(1e-30)) + K.LOG_INV_ALPHA_MIN)
            half_x = torch.sqrt(level.clamp_min(0) * splat["cov"][:, 0, 0])
            half_y = torch.sqrt(level.clamp_min(0) * splat["cov"][:, 1, 1])
            centre = splat["means2d"]
            on_screen = ((torch.ceil(centre[:, 0] - half_x - 0.5) <= width - 1) & (torch.floor(centre[:, 0] + half_x - 0.5) >= 0)
                         & (torch.ceil(centre[:, 1] - half_y - 0.5) <= height - 1) & (torch.floor(centre[:, 1] + half_y - 0.5) >= 0))
            keep = visible & on_screen
            radius = torch.ceil(torch.maximum(half_x, half_y)).clamp(max=2**30)
            all_radii.append(torch.where(keep, radius, torch.zeros_like(radius)).to(torch.int32))
    meta = {
        "means2d": means2d,
        "radii": torch.stack(all_radii),
        "depths": torch.stack([splat["depth"] for splat in splats]),
        "median_ids": torch.stack(median_ids),
    }
    return torch.stack(renders), torch.stack(alphas), meta
