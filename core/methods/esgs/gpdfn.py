"""GPDFN: Gaussian-parameter deformable fusion (the ESGS neighbour-fusion module).

How we read the paper (its Section 3.4 gives the idea, not every layer):

1. **Voxelize.** Gaussian space is cut into cubic voxels of side ``voxel_size``. Each Gaussian
   has a parameter vector (position relative to its voxel centre in voxel units, log-scale
   relative to the voxel size, unit quaternion, opacity logit, SH DC colour: D = 14). The
   vectors of the Gaussians in a voxel are averaged into that voxel's feature (plus an
   occupancy channel).
2. **Deformable sampling.** Each Gaussian looks at ``fused_k - 1`` neighbouring places:
   ``mean + voxel_size * (base_offset_k + delta_k(params))``. ``base_offset_k`` are learnable
   shared offsets (initialised to unit steps along +x, -x, +y, -y: terrain continues
   sideways), ``delta_k`` a per-Gaussian learnable correction predicted from its own
   parameters (deformable-convolution style, bounded by tanh). The feature of the voxel
   holding each place is read, weighted by a Gaussian kernel of the distance to that voxel's
   centroid, so the offsets receive gradients.
3. **1D convolution + attention.** The ``[fused_k, D + 1]`` tensor (the Gaussian itself first,
   then its samples) goes through pointwise 1D convolutions along the fused axis, an
   attention score per entry (softmax over the fused entries) weights them, and a linear
   head turns the fused feature into **residuals** of the rendering parameters (SH DC colour,
   opacity logit, log-scales), added before rasterization.

The head starts at zero, so at initialisation the module is the identity and cannot hurt
early training. ``fused_k = 1`` means no fusion (the 3DGS baseline, as the paper's Table 9
row 1). Voxel membership is checked at every forward against the current positions: the
voxel table (a hash table of the occupied voxels, :mod:`.gpdfn_kernels`) is reused while no
Gaussian has changed voxel and rebuilt otherwise (after densification, pruning, or any move
across a voxel face), so the reuse is exact.

Cost (see docs/esgs.md): the first pointwise convolution is linear, so it is applied once per
voxel and gathered for the sampled rows; the rest of the fused stack has a hand-written
backward (:class:`_FusionCore`, on the CPU Numba kernels) that avoids the slow paths of the
generic one. On the CPU the voxels' mean features and each fused Gaussian's sampling (features,
offset head, voxel reads, own first layer) are Numba kernels too (:class:`_VoxelMeans`,
:class:`_Sampling`); elsewhere the same maths runs as torch statements (:meth:`GPDFN._sample`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from torch import nn

from . import gpdfn_fusion_kernels as fusion_kernels
from . import gpdfn_kernels as kernels
from . import gpdfn_sampling_kernels as sampling_kernels
from .gpdfn_settings import GPDFNConfig

FEATURE_DIM = 14  # position 3, log-scale 3, quaternion 4, opacity 1, SH DC 3
#: The head's output row of the opacity residual (outputs: SH DC 3, opacity 1, log-scale 3).
_OPACITY_OUTPUT = 3
_BASE_DIRECTIONS = ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0))


def automatic_voxel_size(means: torch.Tensor, sample: int = 20000, seed: int = 0) -> float:
    """Twice the median nearest-neighbour distance of (a sample of) the Gaussian centres."""
    from scipy.spatial import cKDTree

    points = means.detach().cpu().double().numpy()
    if len(points) < 2:
        return 1.0
    if len(points) > sample:
        generator = torch.Generator().manual_seed(seed)
        points = points[torch.randperm(len(points), generator=generator)[:sample].numpy()]
    distances, _ = cKDTree(points).query(points, k=2)
    spacing = float(torch.tensor(distances[:, 1]).median())
    return 2.0 * spacing if spacing > 0 else 1.0


def _voxel_keys(coords: torch.Tensor) -> torch.Tensor:
    """Pack int64 voxel coordinates [..., 3] into one int64 key (21 bits per axis, as the kernels)."""
    offset = 1 << 20
    c = (coords + offset).clamp(0, (1 << 21) - 1)
    return (c[..., 0] << 42) | (c[..., 1] << 21) | c[..., 2]


@dataclass
class VoxelTable:
    """Occupied voxels of one Gaussian set (see :mod:`.gpdfn_kernels`).

    coordinates [N, 3] int64 voxel of each Gaussian; keys [N] int64 packed (a NumPy array on
    the CPU path, a tensor on the torch path); inverse [N] int64 voxel id of each Gaussian;
    counts [V] Gaussians per voxel (float). Voxel ids run in order of first appearance on both
    paths. How :meth:`lookup` finds a voxel depends on where the Gaussians live:

    - CPU (Numba): ``slots`` [S, 2] int64, the hash table (key, voxel id) it probes;
    - any other device (torch): ``sorted_keys`` [V] and ``sorted_ids`` [V], the distinct keys in
      ascending order and their voxel ids, searched with ``torch.searchsorted``. On a GPU this
      keeps the table and its lookups on the device: the Numba path copied every centre and
      every sample point to the host and back, twice per step.
    """

    voxel_size: float
    coordinates: torch.Tensor
    keys: np.ndarray | torch.Tensor
    inverse: torch.Tensor
    counts: torch.Tensor
    slots: Optional[np.ndarray] = None
    sorted_keys: Optional[torch.Tensor] = None
    sorted_ids: Optional[torch.Tensor] = None

    @staticmethod
    def build(means: torch.Tensor, voxel_size: float, previous: Optional["VoxelTable"] = None,
              use_torch: Optional[bool] = None) -> "VoxelTable":
        """Voxel table of the centres ``means`` [N, 3] (no gradient).

        ``previous``: the table of an earlier call. When every centre still lies in the voxel
        it had then (same count, equal keys), its lookup structure, inverse and counts are
        reused: they depend only on the keys, so the reuse is exact. ``use_torch``: the torch
        path (default: wherever ``means`` is not on the CPU); both paths give the same table.
        """
        if use_torch is None:
            use_torch = means.device.type != "cpu"
        if use_torch:
            return VoxelTable._build_torch(means, voxel_size, previous)
        points = means.detach().cpu().contiguous().numpy()
        coordinates, keys = kernels.voxel_coordinates(points, points.dtype.type(voxel_size))
        coordinates_t = torch.from_numpy(coordinates).to(means.device)
        if previous is not None and previous.slots is not None and previous.voxel_size == voxel_size \
                and previous.keys.shape == keys.shape and previous.counts.dtype == means.dtype \
                and previous.counts.device == means.device and np.array_equal(previous.keys, keys):
            return VoxelTable(voxel_size, coordinates_t, keys, previous.inverse, previous.counts, previous.slots)
        slots, inverse = kernels.build_table(keys)
        inverse_t = torch.from_numpy(inverse).to(means.device)
        counts = torch.bincount(inverse_t).to(means.dtype)
        return VoxelTable(voxel_size, coordinates_t, keys, inverse_t, counts, slots)

    @staticmethod
    def _build_torch(means: torch.Tensor, voxel_size: float, previous: Optional["VoxelTable"]) -> "VoxelTable":
        points = means.detach()
        # floor(p / size) in the positions' precision, as the Numba kernel computes it
        coordinates = torch.floor(points / torch.tensor(voxel_size, dtype=points.dtype, device=points.device)).long()
        keys = _voxel_keys(coordinates)
        if previous is not None and previous.sorted_keys is not None and previous.voxel_size == voxel_size \
                and previous.keys.shape == keys.shape and previous.counts.dtype == means.dtype \
                and previous.counts.device == means.device and torch.equal(previous.keys, keys):
            return VoxelTable(voxel_size, coordinates, keys, previous.inverse, previous.counts,
                              sorted_keys=previous.sorted_keys, sorted_ids=previous.sorted_ids)
        sorted_keys, sorted_inverse = torch.unique(keys, sorted=True, return_inverse=True)
        # ids by first appearance (as the hash table gives them), not by key order
        positions = torch.arange(len(keys), device=keys.device)
        first = torch.full((len(sorted_keys),), len(keys), dtype=torch.long, device=keys.device)
        first = first.scatter_reduce(0, sorted_inverse, positions, reduce="amin")
        sorted_ids = torch.empty_like(first)
        sorted_ids[torch.argsort(first)] = torch.arange(len(first), device=keys.device)
        inverse = sorted_ids[sorted_inverse]
        counts = torch.bincount(inverse, minlength=len(sorted_keys)).to(means.dtype)
        return VoxelTable(voxel_size, coordinates, keys, inverse, counts, sorted_keys=sorted_keys,
                          sorted_ids=sorted_ids)

    def lookup(self, points: torch.Tensor) -> torch.Tensor:
        """Voxel id of each point [M, 3] -> [M] int64, -1 where the voxel is empty."""
        if self.sorted_keys is not None:
            detached = points.detach()
            size = torch.tensor(self.voxel_size, dtype=detached.dtype, device=detached.device)
            keys = _voxel_keys(torch.floor(detached / size).long())
            where = torch.searchsorted(self.sorted_keys, keys).clamp_(max=len(self.sorted_keys) - 1)
            hit = self.sorted_keys[where] == keys
            return torch.where(hit, self.sorted_ids[where], torch.full_like(where, -1))
        array = points.detach().cpu().contiguous().numpy()
        found = kernels.lookup(array, array.dtype.type(self.voxel_size), self.slots)
        return torch.from_numpy(found).to(points.device)


#: Gaussians per block of the fused stack: a block's [K, B, H] temporaries (~0.8 MB at K = 3,
#: H = 16) stay in the CPU cache, where the whole-set tensors (~19 MB each at 100k Gaussians)
#: made every elementwise pass a trip to memory and a fresh allocation (page faults).
#: Measured at 100k Gaussians: 2048 to 16384 all within noise; the whole set at once ~1.6x slower.
#: On a GPU the blocks only multiply kernel launches, so the whole set goes at once there.
FUSION_BLOCK = 4096


def add_rows_(target: torch.Tensor, index: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
    """``target.index_add_(0, index, source)`` for 2D tensors; on the CPU by :func:`.gpdfn_kernels.add_rows`
    (the rows added in index order: the same sums on every run), elsewhere by torch. Returns
    ``target``. For GPDFN's own ids only: the kernel does not check that ``index`` is in range."""
    if target.device.type == "cpu" and target.is_contiguous() and source.dtype == target.dtype \
            and target.dtype in (torch.float32, torch.float64) and index.dtype == torch.int64:
        kernels.add_rows(target.detach().numpy(), index.contiguous().numpy(), source.detach().contiguous().numpy())
        return target
    return target.index_add_(0, index, source)


class _RowSums(torch.autograd.Function):
    """[V, D] sums of the rows of ``values`` [N, D] by group ``inverse`` [N] (ids < V): ``index_add``
    with :func:`add_rows_` forward; backward the gather ``grad[inverse]``."""

    @staticmethod
    def forward(ctx, values: torch.Tensor, inverse: torch.Tensor, groups: int) -> torch.Tensor:
        ctx.save_for_backward(inverse)
        return add_rows_(values.new_zeros(groups, values.shape[1]), inverse, values.detach())

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (inverse,) = ctx.saved_tensors
        return grad.index_select(0, inverse), None, None


def _fusion_kernels_apply(tensor: torch.Tensor) -> bool:
    """Whether :class:`_FusionCore` runs on ``tensor`` with the Numba kernels (CPU, float32/64)."""
    return tensor.device.type == "cpu" and tensor.dtype in (torch.float32, torch.float64)


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().contiguous().numpy()


def _fusion_block(tensor: torch.Tensor) -> int:
    """Gaussians per block of :class:`_FusionCore` for tensors on ``tensor``'s device."""
    return FUSION_BLOCK if tensor.device.type == "cpu" else max(int(tensor.shape[0]), 1)


def _fusion_forward_block(own, voxel_projection, index, weight, bias1, weight2, bias2, attention_weight,
                          attention_bias, summary):
    """One block of :class:`_FusionCore`'s forward up to the attention-weighted ``summary`` [B, H]
    (written in place) -> (first, second, attention, gathered): ``gathered`` [K-1, B, H] the
    sampled voxels' projections, kept for the kernel weights' gradient (gathering them again
    in the backward cost one more index_select per block).

    Layout is entry-major, ``[K, B, H]`` (row k = 0 the Gaussian itself), so that every
    per-entry slice is contiguous and the softmax runs over the leading axis (a softmax
    over the short last axis of ``[B, K]``, and writes into strided slices, were the slow
    paths). index, weight: [K-1, B].
    """
    count, hidden = own.shape
    fused = index.shape[0] + 1
    first = torch.empty(fused, count, hidden, dtype=own.dtype, device=own.device)
    first[0] = own
    # index_select, not voxel_projection[index]: advanced indexing with a 2D index was ~20x slower
    gathered = voxel_projection.index_select(0, index.reshape(-1)).view(fused - 1, count, hidden)
    torch.mul(gathered, weight.unsqueeze(2), out=first[1:])
    first[1:] += bias1
    first.relu_()
    second = torch.addmm(bias2, first.view(-1, hidden), weight2.t()).relu_()  # [K B, H]
    stack = second.view(fused, count, hidden)
    scores = (torch.mv(second, attention_weight) + attention_bias).view(fused, count)
    attention = torch.softmax(scores, dim=0)  # [K, B]
    torch.mul(stack[0], attention[0].unsqueeze(1), out=summary)
    for k in range(1, fused):
        summary.addcmul_(stack[k], attention[k].unsqueeze(1))
    return first, second, attention, gathered


class _FusionCore(torch.autograd.Function):
    """Pointwise 1D convolutions, attention and head over the fused stack of K entries per Gaussian.

    Same maths as ``head(sum_k softmax_k(attention(h_k)) h_k)`` with ``h_k = embed(x_k)``
    written with autograd, but the first layer comes in already applied: entry 0 (the
    Gaussian itself) as ``own [N, H]`` and entries 1..K-1 (the sampled voxels) as
    ``weight * voxel_projection[index] + bias1``. The first layer is linear, so applying it
    to the V voxel features once and gathering costs far less than applying it to N (K - 1)
    gathered rows. On the CPU (float32/64) the stack runs in the Numba kernels of
    :mod:`.gpdfn_fusion_kernels`, one Gaussian's stack at a time, keeping nothing between the
    forward and the backward but the inputs (the backward recomputes each stack). Elsewhere the
    Gaussians go through in torch blocks of :data:`FUSION_BLOCK` (each block's temporaries stay
    in the CPU cache; on a GPU one block); the forward keeps each block's activations when a
    gradient is needed and the backward differentiates block by block by hand. The linear head
    runs once on the summaries of all Gaussians. Weight gradients are summed chunk by chunk /
    block by block in a fixed order: deterministic.

    Inputs: own [N, H] (first layer of the Gaussian's own entry, bias included),
    voxel_projection [V, H], index [K-1, N] int64 (clamped to valid ids), weight [K-1, N]
    (kernel weights, 0 for empty voxels), bias1 [H], weight2 [H, H], bias2 [H],
    attention_weight [H], attention_bias [] , head_weight [O, H], head_bias [O].
    Output: [N, O].
    """

    @staticmethod
    def forward(ctx, own, voxel_projection, index, weight, bias1, weight2, bias2, attention_weight, attention_bias,
                head_weight, head_bias):
        count, hidden = own.shape
        parameters = (bias1, weight2, bias2, attention_weight, attention_bias, head_weight, head_bias)
        ctx.kernels = _fusion_kernels_apply(own)
        if ctx.kernels:
            # the whole stack per Gaussian in Numba (gpdfn_fusion_kernels): nothing kept but the inputs
            summaries = torch.from_numpy(fusion_kernels.fusion_forward(
                *(_numpy(t) for t in (own, voxel_projection, index, weight, bias1, weight2, bias2,
                                      attention_weight, attention_bias.reshape(1))), fusion_kernels.CHUNK))
            ctx.save_for_backward(own, voxel_projection, index, weight, summaries, *parameters)
            return torch.addmm(head_bias, summaries, head_weight.t())
        # the attention-weighted summaries of all blocks in one tensor, so the linear head is one
        # matrix product (and its gradients two) instead of one per block
        summaries = own.new_empty(count, hidden)
        saved = []
        keep = any(ctx.needs_input_grad)
        ctx.block = block_size = _fusion_block(own)
        for start in range(0, count, block_size):
            block = slice(start, start + block_size)
            outputs = _fusion_forward_block(own[block], voxel_projection, index[:, block], weight[:, block],
                                            *parameters[:5], summaries[block])
            if keep:
                saved.append(outputs)
        ctx.blocks = saved
        ctx.save_for_backward(own, voxel_projection, index, weight, summaries, *parameters)
        return torch.addmm(head_bias, summaries, head_weight.t())

    @staticmethod
    def backward(ctx, grad_result):
        own, voxel_projection, index, weight, summaries, *parameters = ctx.saved_tensors
        bias1, weight2, bias2, attention_weight, attention_bias, head_weight, head_bias = parameters
        count, hidden = own.shape
        fused = index.shape[0] + 1
        grad_result = grad_result.contiguous()
        grad_voxel_projection = torch.zeros_like(voxel_projection) if ctx.needs_input_grad[1] else None
        grads = [torch.zeros_like(p) for p in parameters]
        grad_bias1, grad_weight2, grad_bias2, grad_attention_weight, grad_attention_bias, grad_head_weight, \
            grad_head_bias = grads
        grad_head_weight.addmm_(grad_result.t(), summaries)
        grad_head_bias.add_(grad_result.sum(0))
        grad_summaries = grad_result @ head_weight  # [N, H]
        if ctx.kernels:
            (grad_own, grad_weight, grad_rows, *kernel_grads) = fusion_kernels.fusion_backward(
                _numpy(grad_summaries), *(_numpy(t) for t in (own, voxel_projection, index, weight, bias1, weight2,
                                                              bias2, attention_weight, attention_bias.reshape(1))),
                fusion_kernels.CHUNK)
            for grad, value in zip(grads[:5], kernel_grads):
                grad.copy_(torch.from_numpy(value).view_as(grad))
            if grad_voxel_projection is not None:
                add_rows_(grad_voxel_projection, index.reshape(-1), torch.from_numpy(grad_rows).view(-1, hidden))
            return (torch.from_numpy(grad_own), grad_voxel_projection, None,
                    torch.from_numpy(grad_weight) if ctx.needs_input_grad[3] else None, *grads)
        grad_own = torch.empty_like(own)
        grad_weight = torch.empty_like(weight) if ctx.needs_input_grad[3] else None
        for start in range(0, count, ctx.block):
            block = slice(start, start + ctx.block)
            block_weight = weight[:, block]
            first, second, attention, gathered = ctx.blocks[start // ctx.block]
            block_index = index[:, block].reshape(-1)
            rows = attention.shape[1]
            grad_summary = grad_summaries[block]  # [B, H]
            stack = second.view(fused, rows, hidden)
            # softmax backward, [K, B]: d score_k = p_k (h_k . g' - summary . g'), where
            # summary . g' = sum_k p_k (h_k . g') as summary = sum_k p_k h_k
            along = (stack * grad_summary).sum(2)
            grad_scores = attention * (along - (attention * along).sum(0))
            grad_attention_weight.addmv_(second.t(), grad_scores.view(-1))
            grad_attention_bias.add_(grad_scores.sum())
            # d h_k = p_k g' + d score_k * attention_weight, then through the second ReLU
            # (threshold_backward: a boolean-mask fill was ~20x slower)
            grad_second = attention.unsqueeze(2) * grad_summary
            grad_second.addcmul_(grad_scores.unsqueeze(2), attention_weight)
            grad_second = torch.ops.aten.threshold_backward(grad_second.view(-1, hidden), second, 0)
            flat_first = first.view(-1, hidden)
            grad_weight2.addmm_(grad_second.t(), flat_first)
            grad_bias2.add_(grad_second.sum(0))
            grad_first = torch.ops.aten.threshold_backward(grad_second @ weight2, flat_first, 0)
            grad_first = grad_first.view(fused, rows, hidden)
            grad_own[block] = grad_first[0]
            grad_sampled = grad_first[1:]  # [K-1, B, H]
            grad_bias1.add_(grad_sampled.reshape(-1, hidden).sum(0))
            if grad_weight is not None:
                grad_weight[:, block] = (grad_sampled * gathered).sum(2)
            if grad_voxel_projection is not None:
                add_rows_(grad_voxel_projection, block_index,
                          (grad_sampled * block_weight.unsqueeze(2)).view(-1, hidden))
        return (grad_own, grad_voxel_projection, None, grad_weight, *grads)


def _sampling_kernels_apply(tensor: torch.Tensor, table: VoxelTable) -> bool:
    """Whether :class:`_Sampling` runs on ``tensor`` (CPU, float32/64, the Numba hash table)."""
    return _fusion_kernels_apply(tensor) and table.slots is not None


def _voxel_scalars(means: torch.Tensor, voxel: float) -> tuple[np.floating, np.floating]:
    """(voxel, log(voxel)) as NumPy scalars of the positions' dtype, rounded as the torch statement
    rounds them, for the kernels of :mod:`.gpdfn_sampling_kernels`."""
    dtype = np.float64 if means.dtype == torch.float64 else np.float32
    return dtype(voxel), dtype(float(torch.log(torch.tensor(voxel, dtype=means.dtype))))


class _VoxelMeans(torch.autograd.Function):
    """Each voxel's mean feature vector [V, 14] (differentiable) and centroid [V, 3] (constant) from
    every Gaussian's parameters, in the Numba kernels of :mod:`.gpdfn_sampling_kernels` (CPU): the
    torch statement builds every Gaussian's features ([N, 14], a concatenation and its backward's
    copies) and sums them by voxel. Inputs: means, log_scales, unit quats, opacity_logits [N],
    sh_dc [N, 3]; the voxel table (constant); the voxel side (float)."""

    @staticmethod
    def forward(ctx, means, log_scales, quats, opacity_logits, sh_dc, table, voxel):
        scalars = _voxel_scalars(means, voxel)
        features, centroids = sampling_kernels.voxel_means(
            *(_numpy(t) for t in (means, log_scales, quats, opacity_logits, sh_dc)), table.coordinates.numpy(),
            _numpy(table.inverse), _numpy(table.counts), *scalars)
        centroids_t = torch.from_numpy(centroids)
        ctx.mark_non_differentiable(centroids_t)
        ctx.table, ctx.voxel = table, scalars[0]
        return torch.from_numpy(features), centroids_t

    @staticmethod
    def backward(ctx, grad_features, grad_centroids):
        grads = sampling_kernels.voxel_means_backward(_numpy(grad_features), _numpy(ctx.table.inverse),
                                                      _numpy(ctx.table.counts), ctx.voxel)
        return (*(torch.from_numpy(g) for g in grads), None, None)


class _Sampling(torch.autograd.Function):
    """The per-Gaussian sampling of :meth:`GPDFN.forward` in the Numba kernels of
    :mod:`.gpdfn_sampling_kernels` (CPU): the fused Gaussians' features, offset head, sample
    points, voxel reads and kernel weights, and their own first-layer values. Same maths as the
    torch statement in :meth:`GPDFN._sample` (the path elsewhere). Inputs: the Gaussians' means,
    log_scales, unit quats [N, 4], opacity_logits [N], sh_dc [N, 3]; the offset head's weight and
    bias, the base offsets, the first layer's weight [H, 15] and bias; rows [M] int64 (sorted and
    unique: the backward writes each row's gradient once, it does not add them); the voxel table and
    its centroids [V, 3] (constants); voxel side and largest shift (floats). Outputs: own [M, H],
    index [K-1, M] int64, weight [K-1, M]. Kept for the backward: the offset head's tanh
    [3(K-1), M] and the samples' offsets to their centroids [K-1, 3, M] (~50 bytes per fused
    Gaussian at K = 3), so the backward neither takes a tanh nor reads the voxel table again.
    """

    @staticmethod
    def forward(ctx, means, log_scales, quats, opacity_logits, sh_dc, offset_weight, offset_bias, base_offsets,
                first_weight, first_bias, rows, table, centroids, voxel, max_shift):
        if rows.numel() > 1 and not bool((rows[1:] > rows[:-1]).all()):
            raise ValueError("GPDFN's sampling kernels need sorted, unique rows (each row's gradient is written once)")
        scalars = _voxel_scalars(means, voxel)
        shift_scale = type(scalars[0])(max_shift * voxel)
        gaussians = tuple(_numpy(t) for t in (means, log_scales, quats, opacity_logits, sh_dc))
        rows_array, coordinates = _numpy(rows), table.coordinates.numpy()
        own, pre = sampling_kernels.sampling_layers(
            *gaussians, rows_array, coordinates, _numpy(offset_weight), _numpy(offset_bias), _numpy(first_weight),
            _numpy(first_bias), *scalars, sampling_kernels.CHUNK)
        shift = torch.from_numpy(pre).tanh_()
        index, squared, delta = sampling_kernels.sampling_reads(
            gaussians[0], rows_array, table.slots, _numpy(centroids), _numpy(base_offsets), shift.numpy(),
            scalars[0], shift_scale, sampling_kernels.CHUNK)
        index_t = torch.from_numpy(index)
        weight = torch.from_numpy(squared).mul_(-0.5).exp_()  # 0 where the voxel is empty (squared = inf)
        ctx.mark_non_differentiable(index_t)
        ctx.save_for_backward(means, log_scales, quats, opacity_logits, sh_dc, offset_weight, first_weight, rows,
                              weight, shift, torch.from_numpy(delta))
        ctx.coordinates, ctx.scalars = table.coordinates, (*scalars, shift_scale)
        return torch.from_numpy(own), index_t, weight

    @staticmethod
    def backward(ctx, grad_own, grad_index, grad_weight):
        (means, log_scales, quats, opacity_logits, sh_dc, offset_weight, first_weight, rows, weight, shift,
         delta) = ctx.saved_tensors
        # (autograd materialises an unused output's gradient as zeros: neither comes as None)
        grads = sampling_kernels.sampling_backward(
            *(_numpy(t) for t in (grad_own, grad_weight, weight, delta, shift, means, log_scales, quats,
                                  opacity_logits, sh_dc, rows)),
            ctx.coordinates.numpy(), _numpy(offset_weight), _numpy(first_weight), *ctx.scalars,
            sampling_kernels.CHUNK)
        return (*(torch.from_numpy(g) for g in grads), None, None, None, None, None)


class GPDFN(nn.Module):
    """Neighbour fusion of Gaussian parameters into rendering-parameter residuals."""

    def __init__(self, config: GPDFNConfig | None = None):
        super().__init__()
        self.config = config or GPDFNConfig()
        self.config.validate()
        self.voxel_size = float(self.config.gpdfn_voxel_size)
        neighbours = self.config.fused_k - 1
        self.enabled = neighbours > 0
        self._table: Optional[VoxelTable] = None  # voxel table of the last forward (exact reuse)
        if not self.enabled:
            return
        directions = [_BASE_DIRECTIONS[i % 4] for i in range(neighbours)]
        scale = [1.0 + i // 4 for i in range(neighbours)]
        base = torch.tensor(directions) * torch.tensor(scale).unsqueeze(1)
        self.base_offsets = nn.Parameter(base.float())  # [K-1, 3] in voxels
        self.offset_head = nn.Linear(FEATURE_DIM, 3 * neighbours)
        nn.init.zeros_(self.offset_head.weight)
        nn.init.zeros_(self.offset_head.bias)
        hidden = self.config.gpdfn_hidden
        # pointwise 1D convolutions along the fused axis, written as Linear layers on
        # [N, K, D] (the same operation, and much faster on the CPU than Conv1d here)
        self.embed = nn.Sequential(
            nn.Linear(FEATURE_DIM + 1, hidden), nn.ReLU(),
            nn.Linear(hidden, hidden), nn.ReLU(),
        )
        self.attention = nn.Linear(hidden, 1)
        self.head = nn.Linear(hidden, 7)  # sh_dc 3, opacity 1, log-scale 3
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def reset_opacity_residual(self) -> None:
        """Zero the head's opacity output (its weights and bias), as at initialisation.

        The trainer's opacity reset clamps every Gaussian's own opacity to 0.01 so that each
        one earns its opacity again. GPDFN learns an opacity residual of its own (-0.1 to -1.4 in
        logit at the median on the runs we read, lowering every Gaussian), which is harmless at trained
        opacities but takes a reset Gaussian from 0.01 to ~0.002, below the rasterizer's 1/255
        cull: such a Gaussian is drawn nowhere, gets no gradient and stays invisible, and with
        most of a scene's Gaussians culled a run never recovered (docs/esgs.md, "GPDFN and the
        opacity reset"). Zeroed, the residual renders the reset opacities as 3DGS does and is
        learnt again from there.
        """
        with torch.no_grad():
            self.head.weight[_OPACITY_OUTPUT].zero_()
            self.head.bias[_OPACITY_OUTPUT].zero_()

    # ----------------------------------------------------------------------------------
    def gaussian_features(self, means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                          opacity_logits: torch.Tensor, sh_dc: torch.Tensor,
                          coordinates: Optional[torch.Tensor] = None, unit_quats: bool = False) -> torch.Tensor:
        """[N, 14] normalised parameter vectors (positions in voxel units inside the voxel).

        ``coordinates`` [N, 3]: the voxel of each Gaussian when already known (the voxel table's).
        ``unit_quats``: ``quats`` are already ``q / max(|q|, 1e-12)`` (the renderer's), not normalised again.
        """
        voxel = self.voxel_size
        if coordinates is None:
            coordinates = torch.floor(means.detach() / voxel)
        local = means / voxel - coordinates.to(means.dtype) - 0.5
        if not unit_quats:
            quats = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        relative_scale = log_scales - torch.log(torch.tensor(voxel, dtype=means.dtype))
        return torch.cat([local, relative_scale, quats, opacity_logits.reshape(-1, 1), sh_dc], dim=-1)

    def voxel_table(self, means: torch.Tensor) -> VoxelTable:
        """The voxel table of ``means`` [N, 3], reusing the last one when no Gaussian changed voxel."""
        self._table = VoxelTable.build(means, self.voxel_size, self._table)
        return self._table

    def sample_voxels(self, points: torch.Tensor, table: VoxelTable,
                      centroids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Soft read places: points [M, 3] -> (voxel index [M] int64, kernel weight [M]).

        The voxel containing each point is looked up; its weight is a Gaussian kernel of the
        distance from the point to the voxel's centroid (in voxel units), so the sampling place
        (and the learnable offsets behind it) receives gradients. One read per sample: eight
        times cheaper than trilinear interpolation over voxel corners. Empty voxels give weight
        0 (and index 0, a valid row to gather from).
        """
        found = table.lookup(points)
        present = found >= 0
        index = found.clamp_min(0)
        offset = (points - centroids.index_select(0, index)) / self.voxel_size
        weight = torch.exp(-0.5 * (offset * offset).sum(dim=1)) * present.to(points.dtype)
        return index, weight

    def _voxel_averages(self, gaussians: tuple[torch.Tensor, ...], table: VoxelTable, kernels: bool
                        ) -> tuple[torch.Tensor, torch.Tensor, Optional[torch.Tensor]]:
        """(voxel_features [V, 14], centroids [V, 3] detached, every Gaussian's features [N, 14] or
        None): the voxels' means; ``kernels``: from the parameters in Numba (no per-Gaussian
        features), else through the features in torch. ``gaussians``: means, log_scales, unit
        quats, opacity_logits, sh_dc."""
        if kernels:
            return (*_VoxelMeans.apply(*gaussians, table, self.voxel_size), None)
        features = self.gaussian_features(*gaussians, table.coordinates, unit_quats=True)
        per_voxel = table.counts.unsqueeze(1)
        voxel_features = _RowSums.apply(features, table.inverse, table.counts.shape[0]) / per_voxel
        centroids = add_rows_(gaussians[0].new_zeros(table.counts.shape[0], 3), table.inverse,
                             gaussians[0].detach()) / per_voxel
        return voxel_features, centroids, features

    def _sample(self, means: torch.Tensor, features: torch.Tensor, rows: Optional[torch.Tensor], table: VoxelTable,
                centroids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The torch statement of the sampling (the path off the CPU; :class:`_Sampling` on it):
        (own [M, H], index [K-1, M], weight [K-1, M]) of ``rows`` (every Gaussian when None)."""
        if rows is not None:
            # the per-Gaussian work (sampling, fusion and their backward) for the chosen rows only
            features, means = features.index_select(0, rows), means.index_select(0, rows)
        count, neighbours = means.shape[0], self.config.fused_k - 1
        # mean + voxel_size * (base_offset + max_shift * tanh(offset_head(features))), in two passes
        # entry-major [K-1, N, 3], the fusion core's layout (see _fusion_forward_block)
        shift = torch.tanh(self.offset_head(features)).view(count, neighbours, 3).transpose(0, 1)
        base = means.unsqueeze(0) + self.base_offsets.unsqueeze(1) * self.voxel_size
        sample_points = torch.add(base, shift, alpha=self.config.gpdfn_max_shift_voxels * self.voxel_size).reshape(-1, 3)
        index, weight = self.sample_voxels(sample_points, table, centroids)
        first = self.embed[0]
        own = torch.addmm(first.bias + first.weight[:, -1], features, first.weight[:, :-1].t())
        return own, index.view(neighbours, count), weight.view(neighbours, count)

    def forward(self, means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                opacity_logits: torch.Tensor, sh_dc: torch.Tensor, unit_quats: bool = False,
                rows: Optional[torch.Tensor] = None) -> dict[str, torch.Tensor]:
        """Residuals for the rendering parameters.

        Inputs: means [N,3], log_scales [N,3], quats [N,4] (wxyz), opacity_logits [N],
        sh_dc [N,3]. Returns {"sh_dc": [N,3], "opacity_logits": [N], "log_scales": [N,3]}
        to ADD to the Gaussians' own parameters (all zero when disabled or at initialisation).
        ``unit_quats``: ``quats`` are already normalised as ``q / max(|q|, 1e-12)`` (the trainer
        hook passes the renderer's, so a step normalises once; same values and gradients).
        ``rows`` [M] int64 (sorted, unique): fuse only these Gaussians; the others get zero
        residuals. The voxel features still average every Gaussian, so the residuals of
        ``rows`` and every gradient of a loss that reads only them are those of the full
        forward (the trainer hook passes the Gaussians a step can render).
        """
        count = means.shape[0]
        if not self.enabled or count == 0:
            zeros = means.new_zeros
            return {"sh_dc": zeros(count, 3), "opacity_logits": zeros(count), "log_scales": zeros(count, 3)}
        if self.voxel_size <= 0:
            self.voxel_size = automatic_voxel_size(means)
        table = self.voxel_table(means)
        if not unit_quats:
            quats = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        gaussians = (means, log_scales, quats, opacity_logits, sh_dc)
        kernels = _sampling_kernels_apply(means, table)
        voxel_features, centroids, features = self._voxel_averages(gaussians, table, kernels)
        full_count = count
        if rows is not None and rows.numel() == 0:
            zeros = means.new_zeros
            return {"sh_dc": zeros(full_count, 3), "opacity_logits": zeros(full_count), "log_scales": zeros(full_count, 3)}
        # first pointwise convolution over the [features, weight channel] rows: the own row has
        # weight channel 1; a sampled row is weight * [voxel feature, 1], so its first layer is
        # weight * (voxel projection) + bias, with the projection computed once per voxel
        first = self.embed[0]
        voxel_projection = torch.addmm(first.weight[:, -1], voxel_features, first.weight[:, :-1].t())
        if kernels:
            fused_rows = rows if rows is not None else torch.arange(count, device=means.device)
            own, index, weight = _Sampling.apply(
                *gaussians, self.offset_head.weight, self.offset_head.bias, self.base_offsets, first.weight,
                first.bias, fused_rows, table, centroids, self.voxel_size, self.config.gpdfn_max_shift_voxels)
        else:
            own, index, weight = self._sample(means, features, rows, table, centroids)
        second = self.embed[2]
        residual = _FusionCore.apply(own, voxel_projection, index, weight, first.bias, second.weight, second.bias,
                                     self.attention.weight[0], self.attention.bias[0], self.head.weight,
                                     self.head.bias)
        if rows is not None:
            residual = residual.new_zeros(full_count, residual.shape[1]).index_copy(0, rows, residual)
        return {"sh_dc": residual[:, 0:3], "opacity_logits": residual[:, _OPACITY_OUTPUT], "log_scales": residual[:, 4:7]}
