"""CPU backend: Numba projection and tile compositing, both with hand-written backwards.

:class:`_Project` maps the Gaussians into all cameras at once. Per camera,
:class:`_Composite` composites a generic per-Gaussian feature vector (colour, depth,
normal, extra concatenated) from screen-space means, conics and opacities; its backward
returns their gradients. Autograd glues the two together with the SH evaluation and the
per-channel post-processing (background, depth normalisation), which stay in torch.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import ConfigError
from . import constants as K
from . import cpu_kernels as kernels
from . import projection_kernels

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
    tile_order: np.ndarray  # [T] processing order of the tiles
    tile_start: np.ndarray  # [T + 1] start of each tile's list in pair_rank
    pair_rank: np.ndarray  # [P] depth rank of each tile-Gaussian pair
    order: np.ndarray  # [M] Gaussian id of each depth rank
    rank_pair_start: np.ndarray  # [M + 1]
    rank_pairs: np.ndarray  # [P] pair positions of each rank
    pair_gaussian: np.ndarray  # [P] Gaussian id of each pair
    splats: np.ndarray  # [P, 8] screen-space Gaussian of each pair, in tile order
    boxes: np.ndarray  # [P, 4] inclusive pixel bounds of each pair
    centres_x: np.ndarray
    centres_y: np.ndarray
    constants: np.ndarray
    evaluations: int = 0
    median_ids: np.ndarray | None = None  # [H, W] set by the forward pass (see _Composite)

    @property
    def pairs(self) -> int:
        return int(self.pair_rank.shape[0])


def _tile_order(tiles: int) -> np.ndarray:
    """A fixed shuffle of the tiles, so that Numba's equal static chunks of ``prange`` get a
    similar mix of busy and empty tiles (an oblique view is busy at the bottom only)."""
    return np.random.default_rng(12345).permutation(tiles).astype(np.int64)


def _depth_order(index: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """``index`` sorted by ``depth[index]``, ties by index (a stable sort), as int64.

    For float32 depths (all positive here: behind-the-near-plane ones are culled) the bit
    pattern read as an integer increases with the value, so one sort of the 64-bit keys
    (depth bits, index) gives the stable order about 7x faster than a stable argsort.
    """
    values = depth[index]
    if values.dtype == np.float32 and index.size and index.max() < 2**31:
        keys = (values.view(np.int32).astype(np.int64) << 32) | index.astype(np.int64)
        return np.sort(keys) & 0xFFFFFFFF
    return index[np.argsort(values, kind="stable")].astype(np.int64)


def _make_plan(means2d, conics, opacities, depths, valid, cov_diagonal, width, height, tile_size):
    """Cull, bound, depth-sort, pack and bin the Gaussians of one camera.

    Returns the plan and the exact 1/255 level of every Gaussian (for the radii).
    """
    means2d = means2d.detach().numpy()
    np_dtype = means2d.dtype
    count = means2d.shape[0]
    keep = np.empty(count, dtype=np.bool_)
    level = np.empty(count, dtype=np.float64)
    exact_level = np.empty(count, dtype=np.float64)
    boxes = np.empty((count, 4), dtype=np.int32)
    kernels.prepare_splats(means2d, conics.detach().numpy(), opacities.detach().numpy(), cov_diagonal.numpy(),
                           valid.numpy(), width, height, K.LOG_INV_ALPHA_MIN, _LEVEL_SLACK_RELATIVE,
                           _LEVEL_SLACK_ABSOLUTE, K.ALPHA_MIN, keep, level, exact_level, boxes)
    order = _depth_order(np.flatnonzero(keep), depths.detach().numpy())
    splats = np.empty((order.shape[0], kernels.SPLAT_COLUMNS), dtype=np_dtype)
    packed_boxes = np.empty((order.shape[0], 4), dtype=np.int32)
    kernels.pack_splats(order, means2d, conics.detach().numpy(), opacities.detach().numpy(), level, boxes, splats,
                        packed_boxes)
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    tile_start, pair_rank, rank_pair_start, rank_pairs = kernels.bin_gaussians(packed_boxes, tile_size, tiles_x,
                                                                               tiles_y)
    constants = np.zeros(7, dtype=np_dtype)
    constants[kernels.C_HALF] = 0.5
    constants[kernels.C_ONE] = 1.0
    constants[kernels.C_TWO] = 2.0
    constants[kernels.C_ALPHA_MIN] = K.ALPHA_MIN
    constants[kernels.C_ALPHA_MAX] = K.ALPHA_MAX
    constants[kernels.C_T_MIN] = K.TRANSMITTANCE_MIN
    constants[kernels.C_SLACK] = 1e-3
    pair_splats = np.empty((pair_rank.shape[0], kernels.SPLAT_COLUMNS), dtype=np_dtype)
    pair_boxes = np.empty((pair_rank.shape[0], 4), dtype=np.int32)
    kernels.gather_rows(pair_rank, splats, pair_splats)
    kernels.gather_rows(pair_rank, packed_boxes, pair_boxes)
    plan = _Plan(
        width=width, height=height, tile_size=tile_size, tiles_x=tiles_x, tiles_y=tiles_y,
        tile_order=_tile_order(tiles_x * tiles_y), tile_start=tile_start, pair_rank=pair_rank, order=order,
        rank_pair_start=rank_pair_start, rank_pairs=rank_pairs, pair_gaussian=order[pair_rank],
        splats=pair_splats, boxes=pair_boxes,
        centres_x=(np.arange(width) + 0.5).astype(np_dtype), centres_y=(np.arange(height) + 0.5).astype(np_dtype),
        constants=constants,
    )
    return plan, exact_level


class _Composite(torch.autograd.Function):
    """(means2d [N, 2], conics [N, 3], opacities [N], features [N, F]) -> image [H, W, F], alpha [H, W, 1].

    The screen-space values were already packed into ``plan`` (same numbers); the tensors
    are inputs so that autograd routes their gradients.
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, plan: _Plan):
        features_np = features.detach().numpy()
        np_dtype = features_np.dtype
        packed = np.empty((plan.pairs, features_np.shape[1]), dtype=np_dtype)
        kernels.gather_rows(plan.pair_gaussian, np.ascontiguousarray(features_np), packed)
        image = np.zeros((plan.height, plan.width, features_np.shape[1]), dtype=np_dtype)
        transmittance = np.empty((plan.height, plan.width), dtype=np_dtype)
        stop = np.empty((plan.height, plan.width), dtype=np.int64)
        crossing = np.empty((plan.height, plan.width), dtype=np.int64)
        evaluations = np.zeros(plan.tiles_x * plan.tiles_y, dtype=np.int64)
        kernels.composite_forward(plan.tile_order, plan.tile_start, plan.tiles_x, plan.tile_size,
                                  plan.centres_x, plan.centres_y, plan.splats, plan.boxes, packed, plan.constants,
                                  image, transmittance, stop, crossing, evaluations)
        plan.evaluations = int(evaluations.sum())
        crossed = crossing >= 0
        plan.median_ids = np.where(crossed, plan.pair_gaussian[np.where(crossed, crossing, 0)], -1) \
            if plan.pairs else np.full_like(crossing, -1)
        ctx.plan = plan
        ctx.packed = packed
        ctx.transmittance = transmittance
        ctx.stop = stop
        ctx.count = means2d.shape[0]
        alpha = torch.from_numpy(1.0 - transmittance).unsqueeze(-1)
        return torch.from_numpy(image), alpha

    @staticmethod
    def backward(ctx, grad_image, grad_alpha):
        plan: _Plan = ctx.plan
        packed = ctx.packed
        np_dtype = packed.dtype
        channels = packed.shape[1]
        height, width = plan.height, plan.width
        grad_image = (np.zeros((height, width, channels), dtype=np_dtype) if grad_image is None
                      else np.ascontiguousarray(grad_image.detach().numpy(), dtype=np_dtype))
        grad_alpha = (np.zeros((height, width), dtype=np_dtype) if grad_alpha is None
                      else np.ascontiguousarray(grad_alpha.detach().numpy()[..., 0], dtype=np_dtype))
        records = np.empty((plan.pairs, kernels.RECORD_FIXED + channels), dtype=np_dtype)
        kernels.composite_backward(
            plan.tile_order, plan.tile_start, plan.tiles_x, plan.tile_size,
            plan.centres_x, plan.centres_y, plan.splats, plan.boxes, packed, plan.constants,
            ctx.transmittance, ctx.stop, grad_image, grad_alpha, records)
        totals = np.zeros((ctx.count, kernels.RECORD_FIXED + channels), dtype=np_dtype)
        kernels.reduce_records(plan.order, plan.rank_pair_start, plan.rank_pairs, records, totals)
        totals = torch.from_numpy(totals)
        grad_means2d = totals[:, kernels.R_MEAN_X:kernels.R_MEAN_Y + 1]
        grad_conics = totals[:, kernels.R_CONIC_A:kernels.R_CONIC_C + 1]
        grad_opacity = totals[:, kernels.R_OPACITY]
        grad_features = totals[:, kernels.RECORD_FIXED:]
        return grad_means2d, grad_conics, grad_opacity, grad_features, None


class _Project(torch.autograd.Function):
    """Gaussians -> screen space for C cameras (Numba forward and backward).

    Inputs means [N, 3], quats [N, 4], scales [N, 3], opacities [N]; ``cameras`` holds
    viewmats [C, 4, 4], Ks [C, 3, 3] and the settings (no gradient flows to the cameras).
    Outputs means2d [C, N, 2], conics [C, N, 3], opacities [C, N], depths [C, N],
    normals [C, N, 3] (zeros unless requested), and without grad valid [C, N] and the
    dilated covariance diagonal [C, N, 2].
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, cameras):
        viewmats, Ks, settings = cameras
        # The kernels compute in float64 whatever the storage (every load is converted, every
        # store rounded once, as .to() would), so they read the Gaussians and write their outputs
        # in the model's own dtype: float64 copies of the inputs, kept to the backward, and of
        # the outputs cost ~0.2 KB per Gaussian at the step's peak (docs/training.md, "Memory").
        # The price: a second compiled version of this kernel pair for float32 (cached).
        storage = means.dtype
        arrays = [t.detach().to(storage).contiguous().numpy() for t in (means, quats, scales, opacities)]
        views = viewmats.detach().to(torch.float64).contiguous().numpy()
        intrinsics = Ks.detach().to(torch.float64).contiguous().numpy()
        count, cams = means.shape[0], views.shape[0]
        dtype = arrays[0].dtype
        ctx.dtype = storage
        means2d = np.empty((cams, count, 2), dtype=dtype)
        conics = np.empty((cams, count, 3), dtype=dtype)
        effective = np.empty((cams, count), dtype=dtype)
        depths = np.empty((cams, count), dtype=dtype)
        normals = np.zeros((cams, count, 3), dtype=dtype)
        valid = np.empty((cams, count), dtype=np.bool_)
        cov_diagonal = np.empty((cams, count, 2), dtype=dtype)
        projection_kernels.project_forward(*arrays, views, intrinsics, *settings, means2d, conics, effective,
                                           depths, normals, valid, cov_diagonal)
        ctx.arrays = arrays  # views of the inputs when they are contiguous: no copy
        ctx.cameras = (views, intrinsics, settings)
        valid_t, cov_t = torch.from_numpy(valid), torch.from_numpy(cov_diagonal).to(storage)
        ctx.mark_non_differentiable(valid_t, cov_t)
        return (torch.from_numpy(means2d).to(storage), torch.from_numpy(conics).to(storage),
                torch.from_numpy(effective).to(storage), torch.from_numpy(depths).to(storage),
                torch.from_numpy(normals).to(storage), valid_t, cov_t)

    @staticmethod
    def backward(ctx, grad_means2d, grad_conics, grad_opacities, grad_depths, grad_normals, _valid, _cov):
        arrays = ctx.arrays
        views, intrinsics, settings = ctx.cameras
        count, cams = arrays[0].shape[0], views.shape[0]
        dtype = arrays[0].dtype  # the storage of the forward (see there)

        def prepared(gradient, shape):
            if gradient is None:
                return np.zeros(shape, dtype=dtype)
            return np.ascontiguousarray(gradient.detach().numpy(), dtype=dtype)

        out = [np.empty((count, 3), dtype=dtype), np.empty((count, 4), dtype=dtype),
               np.empty((count, 3), dtype=dtype), np.empty(count, dtype=dtype)]
        projection_kernels.project_backward(
            *arrays, views, intrinsics, *settings, prepared(grad_means2d, (cams, count, 2)),
            prepared(grad_conics, (cams, count, 3)), prepared(grad_opacities, (cams, count)),
            prepared(grad_depths, (cams, count)), prepared(grad_normals, (cams, count, 3)), *out)
        return (*(torch.from_numpy(g).to(ctx.dtype) for g in out), None)


def project(means, quats, scales, opacities, viewmats, Ks, width, height, *, near_plane, far_plane, antialiased,
            eps2d, need_normals) -> dict:
    """Numba version of :func:`.projection.project_gaussians` (same outputs)."""
    settings = (int(width), int(height), float(near_plane), float(far_plane),
                float(eps2d if antialiased else K.CLASSIC_DILATION), bool(antialiased), float(K.JACOBIAN_MARGIN),
                bool(need_normals))
    means2d, conics, effective, depths, normals, valid, cov_diagonal = _Project.apply(
        means, quats, scales, opacities, (viewmats, Ks, settings))
    return {"means2d": means2d, "conics": conics, "opacities": effective, "depths": depths,
            "normals": normals if need_normals else None, "valid": valid, "cov_diagonal": cov_diagonal}


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
        raise ConfigError(f"the cpu rasterizer backend needs float32 or float64 tensors, got {means.dtype}",
                          hint="convert the inputs with .float()")
    if means.device.type != "cpu":
        raise ConfigError(f"the cpu rasterizer backend needs CPU tensors, got {means.device}",
                          hint='move them with .cpu() or use backend="cuda"')
    _set_threads(num_threads)
    projected = project(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane=near_plane,
                        far_plane=far_plane, antialiased=antialiased, eps2d=eps2d, need_normals=render_normals)
    means2d = projected["means2d"]
    cameras = viewmats.shape[0]
    renders, alphas, radii, intersections, evaluations, median_ids = [], [], [], [], [], []
    for cam in range(cameras):
        plan, exact_level = _make_plan(means2d[cam], projected["conics"][cam], projected["opacities"][cam],
                                       projected["depths"][cam], projected["valid"][cam],
                                       projected["cov_diagonal"][cam], width, height, tile_size)
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
        radius = np.zeros(means.shape[0], dtype=np.int32)
        if plan.order.size:
            diagonal = projected["cov_diagonal"][cam].numpy()[plan.order].astype(np.float64)
            extent = np.sqrt(exact_level[plan.order, None] * diagonal).max(-1)
            radius[plan.order] = np.ceil(np.minimum(extent, 2.0**30)).astype(np.int32)
        radii.append(torch.from_numpy(radius))
        intersections.append(plan.pairs)
        evaluations.append(plan.evaluations)
        median_ids.append(torch.from_numpy(plan.median_ids))
    meta = {
        "means2d": means2d,
        "radii": torch.stack(radii),
        "depths": projected["depths"].detach(),
        "median_ids": torch.stack(median_ids),
        "tile_size": tile_size,
        "tiles_x": -(-width // tile_size),
        "tiles_y": -(-height // tile_size),
        "n_intersections": intersections,
        "n_evaluations": evaluations,
    }
    return torch.stack(renders), torch.stack(alphas), meta
