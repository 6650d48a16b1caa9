"""CPU backend: torch projection + Numba tile compositing with a hand-written backward.

Per camera, :class:`_Composite` (a ``torch.autograd.Function``) composites a generic
per-Gaussian feature vector (colour, depth, normal, extra concatenated) from screen-space
means, conics and opacities; its backward returns their gradients and autograd carries
them back through the projection and SH evaluation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from . import constants as K
from . import cpu_kernels as kernels
from .projection import project_gaussians

#: Added to the exact level 2 log(255 opacity) so that a pixel skipped without ``exp`` is
#: certainly below alpha 1/255 despite rounding (relative, then absolute).
_LEVEL_SLACK_RELATIVE = 1e-6
_LEVEL_SLACK_ABSOLUTE = 1e-6


@dataclass
class _Plan:
    """Everything the kernels need for one camera, as numpy arrays (no grad)."""

    width: int
    height: int
    tile_size: int
    tiles_x: int
    tiles_y: int
    tile_order: np.ndarray
    tile_start: np.ndarray
    pair_gaussian: np.ndarray
    order: np.ndarray
    gaussian_pair_start: np.ndarray
    gaussian_pairs: np.ndarray
    level: np.ndarray
    box: tuple
    centres_x: np.ndarray
    centres_y: np.ndarray
    constants: np.ndarray

    @property
    def pairs(self) -> int:
        return int(self.pair_gaussian.shape[0])


def _tile_order(tiles: int) -> np.ndarray:
    """A fixed shuffle of the tiles, so that Numba's equal static chunks of ``prange`` get a
    similar mix of busy and empty tiles (an oblique view is busy at the bottom only)."""
    return np.random.default_rng(12345).permutation(tiles).astype(np.int64)


def _make_plan(means2d, conics, opacities, depths, valid, cov_diagonal, width, height, tile_size, dtype):
    """Cull, compute the pixel boxes and bin the Gaussians of one camera into tiles."""
    np_dtype = np.float32 if dtype == torch.float32 else np.float64
    opacity = opacities.detach().numpy().astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        exact_level = 2.0 * (np.log(np.maximum(opacity, 1e-300)) + K.LOG_INV_ALPHA_MIN)
    level = exact_level * (1.0 + _LEVEL_SLACK_RELATIVE) + _LEVEL_SLACK_ABSOLUTE
    centre = means2d.detach().numpy().astype(np.float64)
    diagonal = cov_diagonal.numpy().astype(np.float64)
    keep = valid.numpy() & (opacity >= K.ALPHA_MIN) & np.isfinite(centre).all(-1)
    safe_level = np.where(keep, level, 0.0)
    with np.errstate(invalid="ignore", over="ignore"):
        half_x = np.sqrt(safe_level * diagonal[:, 0])
        half_y = np.sqrt(safe_level * diagonal[:, 1])
        # Far outside the image the exact bound does not matter: clip before integer casts.
        low_x = np.clip(np.ceil(centre[:, 0] - half_x - 0.5), -1, width)
        high_x = np.clip(np.floor(centre[:, 0] + half_x - 0.5), -1, width)
        low_y = np.clip(np.ceil(centre[:, 1] - half_y - 0.5), -1, height)
        high_y = np.clip(np.floor(centre[:, 1] + half_y - 0.5), -1, height)
    keep &= np.isfinite(half_x) & np.isfinite(half_y)
    keep &= (high_x >= 0) & (low_x <= width - 1) & (high_y >= 0) & (low_y <= height - 1) & (low_x <= high_x) \
        & (low_y <= high_y)
    box = tuple(np.where(keep, np.clip(v, 0, limit - 1), 0).astype(np.int64)
                for v, limit in ((low_x, width), (high_x, width), (low_y, height), (high_y, height)))
    index = np.nonzero(keep)[0]
    depth = depths.detach().numpy()
    order = index[np.argsort(depth[index], kind="stable")].astype(np.int64)
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    tile_start, pair_gaussian, gaussian_pair_start, gaussian_pairs = kernels.bin_gaussians(
        order, box[0], box[1], box[2], box[3], tile_size, tiles_x, tiles_y)
    constants = np.zeros(7, dtype=np_dtype)
    constants[kernels.C_HALF] = 0.5
    constants[kernels.C_ONE] = 1.0
    constants[kernels.C_TWO] = 2.0
    constants[kernels.C_ALPHA_MIN] = K.ALPHA_MIN
    constants[kernels.C_ALPHA_MAX] = K.ALPHA_MAX
    constants[kernels.C_T_MIN] = K.TRANSMITTANCE_MIN
    constants[kernels.C_SLACK] = 1e-3
    return _Plan(
        width=width, height=height, tile_size=tile_size, tiles_x=tiles_x, tiles_y=tiles_y,
        tile_order=_tile_order(tiles_x * tiles_y), tile_start=tile_start, pair_gaussian=pair_gaussian,
        order=order, gaussian_pair_start=gaussian_pair_start, gaussian_pairs=gaussian_pairs,
        level=np.where(keep, level, 0.0).astype(np_dtype), box=box,
        centres_x=(np.arange(width) + 0.5).astype(np_dtype), centres_y=(np.arange(height) + 0.5).astype(np_dtype),
        constants=constants,
    ), exact_level


def _soa(means2d, conics, opacities, features):
    """Contiguous numpy views in structure-of-arrays layout."""
    m = means2d.detach().numpy()
    c = conics.detach().numpy()
    return (np.ascontiguousarray(m[:, 0]), np.ascontiguousarray(m[:, 1]), np.ascontiguousarray(c[:, 0]),
            np.ascontiguousarray(c[:, 1]), np.ascontiguousarray(c[:, 2]),
            np.ascontiguousarray(opacities.detach().numpy()), np.ascontiguousarray(features.detach().numpy()))


class _Composite(torch.autograd.Function):
    """(means2d [N, 2], conics [N, 3], opacities [N], features [N, F]) -> image [H, W, F], alpha [H, W, 1]."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, plan: _Plan):
        arrays = _soa(means2d, conics, opacities, features)
        channels = features.shape[1]
        np_dtype = arrays[0].dtype
        image = np.zeros((plan.height, plan.width, channels), dtype=np_dtype)
        transmittance = np.empty((plan.height, plan.width), dtype=np_dtype)
        stop = np.empty((plan.height, plan.width), dtype=np.int64)
        evaluations = np.zeros(plan.tiles_x * plan.tiles_y, dtype=np.int64)
        kernels.composite_forward(plan.tile_order, plan.tile_start, plan.pair_gaussian, plan.tiles_x, plan.tile_size,
                                  plan.centres_x, plan.centres_y, *arrays[:6], plan.level, *plan.box, arrays[6],
                                  plan.constants, image, transmittance, stop, evaluations)
        plan.evaluations = int(evaluations.sum())
        ctx.plan = plan
        ctx.arrays = arrays
        ctx.transmittance = transmittance
        ctx.stop = stop
        ctx.count = means2d.shape[0]
        alpha = torch.from_numpy(1.0 - transmittance).unsqueeze(-1)
        return torch.from_numpy(image), alpha

    @staticmethod
    def backward(ctx, grad_image, grad_alpha):
        plan: _Plan = ctx.plan
        arrays = ctx.arrays
        np_dtype = arrays[0].dtype
        channels = arrays[6].shape[1]
        height, width = plan.height, plan.width
        if grad_image is None:
            grad_image = torch.zeros(height, width, channels, dtype=torch.from_numpy(arrays[0]).dtype)
        if grad_alpha is None:
            grad_alpha = torch.zeros(height, width, 1, dtype=torch.from_numpy(arrays[0]).dtype)
        records = np.empty((plan.pairs, kernels.RECORD_FIXED + channels), dtype=np_dtype)
        kernels.composite_backward(
            plan.tile_order, plan.tile_start, plan.pair_gaussian, plan.tiles_x, plan.tile_size,
            plan.centres_x, plan.centres_y, *arrays[:6], plan.level, *plan.box, arrays[6], plan.constants,
            ctx.transmittance, ctx.stop,
            np.ascontiguousarray(grad_image.detach().numpy(), dtype=np_dtype),
            np.ascontiguousarray(grad_alpha.detach().numpy()[..., 0], dtype=np_dtype),
            np.empty((height, width), dtype=np_dtype), np.empty((height, width, channels), dtype=np_dtype),
            records)
        totals = np.zeros((ctx.count, kernels.RECORD_FIXED + channels), dtype=np_dtype)
        kernels.reduce_records(plan.order, plan.gaussian_pair_start, plan.gaussian_pairs, records, totals)
        totals = torch.from_numpy(totals)
        grad_means2d = totals[:, kernels.R_MEAN_X:kernels.R_MEAN_Y + 1]
        grad_conics = totals[:, kernels.R_CONIC_A:kernels.R_CONIC_C + 1]
        grad_opacity = totals[:, kernels.R_OPACITY]
        grad_features = totals[:, kernels.RECORD_FIXED:]
        return grad_means2d, grad_conics, grad_opacity, grad_features, None


def _set_threads(num_threads: int | None) -> None:
    if num_threads is None:
        return
    import numba

    numba.set_num_threads(max(1, min(int(num_threads), numba.config.NUMBA_NUM_THREADS)))


def rasterize_cpu(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, near_plane, far_plane,
                  sh_degree, backgrounds, render_depth, render_normals, extra, antialiased, eps2d, tile_size,
                  num_threads, evaluate_colors):
    """See :func:`esgs.core.render.rasterization`; returns (render, alpha, meta)."""
    if means.dtype not in (torch.float32, torch.float64):
        means, quats, scales, opacities, colors, viewmats, Ks = (
            t.float() for t in (means, quats, scales, opacities, colors, viewmats, Ks))
    _set_threads(num_threads)
    dtype = means.dtype
    projected = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height,
                                  near_plane=near_plane, far_plane=far_plane, antialiased=antialiased,
                                  eps2d=eps2d, need_normals=render_normals)
    means2d = projected["means2d"]
    cameras = viewmats.shape[0]
    renders, alphas, radii, intersections, evaluations = [], [], [], [], []
    for cam in range(cameras):
        plan, exact_level = _make_plan(means2d[cam], projected["conics"][cam], projected["opacities"][cam],
                                       projected["depths"][cam], projected["valid"][cam],
                                       projected["cov_diagonal"][cam], width, height, tile_size, dtype)
        channels = [evaluate_colors(cam)]
        color_dims = channels[0].shape[1]
        if render_depth:
            channels.append(projected["depths"][cam][:, None])
        if render_normals:
            channels.append(projected["normals"][cam])
        if extra is not None:
            channels.append(extra)
        features = torch.cat(channels, dim=-1).contiguous()
        image, alpha = _Composite.apply(means2d[cam], projected["conics"][cam], projected["opacities"][cam],
                                        features, plan)
        pieces = [image[..., :color_dims]]
        if backgrounds is not None:
            pieces[0] = pieces[0] + (1.0 - alpha) * backgrounds[cam]
        cursor = color_dims
        if render_depth:
            hit = alpha > 0
            safe_alpha = torch.where(hit, alpha, torch.ones_like(alpha))
            pieces.append(torch.where(hit, image[..., cursor:cursor + 1] / safe_alpha, torch.zeros_like(alpha)))
            cursor += 1
        pieces.append(image[..., cursor:])
        renders.append(torch.cat(pieces, dim=-1))
        alphas.append(alpha)
        with np.errstate(invalid="ignore"):
            diagonal = projected["cov_diagonal"][cam].numpy().astype(np.float64)
            extent = np.sqrt(np.maximum(exact_level, 0.0)[:, None] * diagonal).max(-1)
        in_plan = np.zeros(means.shape[0], dtype=bool)
        in_plan[plan.order] = True
        radius = np.where(in_plan, np.ceil(np.minimum(extent, 2.0**30)), 0).astype(np.int32)
        radii.append(torch.from_numpy(radius))
        intersections.append(plan.pairs)
        evaluations.append(getattr(plan, "evaluations", 0))
    meta = {
        "means2d": means2d,
        "radii": torch.stack(radii),
        "depths": projected["depths"].detach(),
        "tile_size": tile_size,
        "tiles_x": -(-width // tile_size),
        "tiles_y": -(-height // tile_size),
        "n_intersections": intersections,
        "n_evaluations": evaluations,
    }
    return torch.stack(renders), torch.stack(alphas), meta
