"""Keep the Gaussians in a spatial (Morton / Z-order) order.

Every per-Gaussian consumer reads memory by Gaussian index: GPDFN's voxel features, hash
lookups and gathers, the rasterizer's projection and per-tile lists. When neighbouring
Gaussians sit next to each other in memory those reads hit the cache; in the order that
densification leaves (clones and split children appended at the end, survivors of a
prune compacted) they jump across the whole set. The trainer therefore sorts the Gaussians
by the Morton code of their quantised centres once after initialisation and after every
densification, moving every per-Gaussian tensor, Adam's moments and the densification
statistics with one permutation (``TrainConfig.spatial_order``).

A Morton code interleaves the bits of the three integer grid coordinates (x in bit 0, y in
bit 1, z in bit 2, then the next bit of each...), so sorting by it walks an octree depth
first: points in the same small cell get consecutive codes.
"""
from __future__ import annotations

from typing import Optional

import torch

#: Grid cells per axis = 2^MORTON_BITS; 3 x 21 bits fill a non-negative int64.
MORTON_BITS = 21


def _spread_bits(values: torch.Tensor) -> torch.Tensor:
    """[N] int64 in [0, 2^21) -> the same bits moved to every third position (bit i -> bit 3i)."""
    x = values & 0x1FFFFF
    x = (x | (x << 32)) & 0x1F00000000FFFF
    x = (x | (x << 16)) & 0x1F0000FF0000FF
    x = (x | (x << 8)) & 0x100F00F00F00F00F
    x = (x | (x << 4)) & 0x10C30C30C30C30C3
    x = (x | (x << 2)) & 0x1249249249249249
    return x


def morton_codes(points: torch.Tensor, bits: int = MORTON_BITS) -> torch.Tensor:
    """Z-order codes of ``points`` [N, 3] -> [N] int64 (no gradient).

    The points are quantised to a grid of 2^bits cubic cells per axis spanning their
    bounding box (the cell size is set by the longest side, so cells stay cubic on flat
    terrain and the vertical axis does not get the same weight as the horizontal ones).
    Non-finite coordinates are put at the box's lower corner.
    """
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [N, 3], got {tuple(points.shape)}")
    if not 1 <= bits <= MORTON_BITS:
        raise ValueError(f"bits must be in [1, {MORTON_BITS}], got {bits}")
    count = points.shape[0]
    if count == 0:
        return torch.zeros(0, dtype=torch.int64, device=points.device)
    coordinates = points.detach().to(torch.float64)
    finite = torch.isfinite(coordinates).all(dim=1)
    if not bool(finite.all()):
        lowest = coordinates[finite].min(dim=0).values if bool(finite.any()) else coordinates.new_zeros(3)
        coordinates = torch.where(finite[:, None], coordinates, lowest)
    lower = coordinates.min(dim=0).values
    side = float((coordinates.max(dim=0).values - lower).max())
    cells = (1 << bits) - 1
    scale = cells / side if side > 0 else 0.0
    grid = torch.floor((coordinates - lower) * scale).clamp_(0, cells).to(torch.int64)
    return _spread_bits(grid[:, 0]) | (_spread_bits(grid[:, 1]) << 1) | (_spread_bits(grid[:, 2]) << 2)


def spatial_order(points: torch.Tensor, bits: int = MORTON_BITS) -> torch.Tensor:
    """The permutation [N] int64 that sorts ``points`` [N, 3] by Morton code.

    Stable: points in the same cell keep their relative order, so the result is a pure
    function of the points and their current order (deterministic, on every device).
    """
    return torch.argsort(morton_codes(points, bits), stable=True)


def is_spatially_ordered(points: torch.Tensor, bits: int = MORTON_BITS) -> bool:
    """True when ``points`` [N, 3] are already in non-decreasing Morton order."""
    codes = morton_codes(points, bits)
    return bool((codes[1:] >= codes[:-1]).all()) if codes.numel() > 1 else True


def reorder_gaussians(model, order: torch.Tensor, optimizer=None, densify_state=None) -> None:
    """Permute every per-Gaussian tensor by ``order`` [N] int64 (row i <- row order[i]).

    ``model`` (:class:`~.gaussians.GaussianModel`) gets new parameters; with ``optimizer``
    (:class:`~.optim.TrainOptimizer`) the per-Gaussian groups and their Adam moments
    (exp_avg, exp_avg_sq) move with them, so the next step is the permuted result of the
    step without reordering; ``densify_state`` (:class:`~.densify.DensifyState`) has its
    gradient accumulators, visibility counts and maximum radii permuted too. Module groups
    (GPDFN's weights) are untouched. Hooks with per-Gaussian state remap it themselves from
    a :class:`~.densify.DensifyReport`'s ``source_index``.
    """
    count = len(model)
    if order.shape != (count,):
        raise ValueError(f"order must have shape ({count},), got {tuple(order.shape)}")
    order = order.to(device=model.device, dtype=torch.int64)
    with torch.no_grad():
        if optimizer is not None:
            missing = set(model.params) - set(optimizer.per_gaussian_names())
            if missing:
                raise ValueError(f"the optimizer has no per-Gaussian group for {', '.join(sorted(missing))}")
            model.set_params(optimizer.select(order))
        else:
            model.set_params({name: torch.nn.Parameter(p.detach()[order].contiguous())
                              for name, p in model.params.items()})
        if densify_state is not None:
            densify_state.select(order)


def sort_gaussians(model, optimizer=None, densify_state=None) -> Optional[torch.Tensor]:
    """Put ``model`` into Morton order of its centres (see :func:`reorder_gaussians`).

    Returns the permutation applied ([N] int64), or None when the model was already in
    order (nothing is touched then, not even the parameter objects).
    """
    order = spatial_order(model.params["means"])
    if bool((order == torch.arange(len(order), device=order.device)).all()):
        return None
    reorder_gaussians(model, order, optimizer, densify_state)
    return order
