"""Scaffold-GS (Lu et al., CVPR 2024) in our trainer: anchors on a voxel grid decode neural Gaussians.

The model is a set of *anchors* at the centres of the voxels that hold SfM points. Each anchor
has a feature vector ``f`` [F], a scaling ``l`` [6] (stored as its log) and ``k`` learned offsets
``O`` [k, 3]. For a camera at ``c``, the anchors in its view decode ``k`` neural Gaussians each:
three small MLPs (one hidden layer of width F, ReLU) read ``[f, (x - c) / |x - c|, |x - c| / extent]``
and give their opacities (tanh), colours (sigmoid, RGB) and covariances (3 scale factors through a
sigmoid times ``l[3:]``, a quaternion); their centres are ``x + O * l[:3]``. Neural Gaussians
whose opacity is not positive are left out of the render.

How it sits in the trainer (no change to the training loop):

- the anchor positions are the run's :class:`~esgs.core.train.gaussians.GaussianModel` centres
  (:meth:`ScaffoldStrategy.prepare_initial` voxelises the SfM points into it); they are fixed
  (the decoder reads them detached), as in the paper; the model's other tensors are unused;
- :class:`ScaffoldStrategy` owns the per-anchor features, offsets and scalings as per-Gaussian
  optimizer groups (so Adam's moments follow anchors when they grow and are pruned), gathers the
  neural Gaussians' gradient and opacity statistics and grows / prunes anchors;
- :class:`ScaffoldHook` owns the MLPs (an optimizer group each, with the paper's decaying rates),
  decodes the visible anchors for every training view in ``before_render`` (what is rasterized),
  adds the volume regulariser, decodes per held-out view in ``view_params`` (the end-of-run
  evaluation) and exports the decoded Gaussians (``export_model``: each anchor decoded for its
  nearest training camera) as a standard 3DGS PLY.

See docs/baselines.md, "Scaffold-GS", for the parameters and what was left out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
import torch
from torch import nn

from ...render.projection import project_points
from ...train.densify import DensifyReport
from ...train.gaussians import PARAMETER_NAMES, GaussianModel, RenderParams, inverse_sigmoid, rgb_to_sh_dc
from ...train.hooks import RunView, StepContext, TrainHook
from ...train.losses import LossContext, LossTerm
from ...train.optim import ExponentialDecay
from ...train.strategy import Strategy, StrategyContext
from .config import ScaffoldGSConfig

#: Learning rates of the reference implementation's defaults (30,000 steps; the decays span the
#: run's length): anchor features, offsets (decaying), scalings, and the three MLPs (decaying).
FEATURE_LR = 0.0075
OFFSET_LR = (0.01, 0.0001)
SCALING_LR = 0.007
OPACITY_MLP_LR = (0.002, 0.00002)
COVARIANCE_MLP_LR = (0.004, 0.004)
COLOUR_MLP_LR = (0.008, 0.00005)

#: Voxels of level m (0 = coarsest) of L are 4^(L-1-m) anchor voxels wide; its gradient threshold is
#: the base one times 2^m, and a candidate voxel survives the random elimination with probability
#: 1 - 0.5^(m+1) (coarse voxels grow fewer anchors).
LEVEL_SIZE_FACTOR = 4
LEVEL_THRESHOLD_FACTOR = 2

#: Anchors closer than this to a camera (scene units) are not decoded for it.
NEAR_PLANE = 0.01

#: The per-anchor optimizer groups the strategy adds, beside the Gaussian model's.
ANCHOR_GROUPS = ("scaffold_features", "scaffold_offsets", "scaffold_log_scaling")


# --- anchors from points ------------------------------------------------------------------
def voxel_size_from_points(points: torch.Tensor | np.ndarray) -> float:
    """The median distance of ``points`` [P, 3] to their nearest other point (scene units).

    Duplicated points (distance 0) are left out; fewer than two distinct points give 1 % of
    the points' bounding-box diagonal, or 0.01 when that is 0 too.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points.detach().cpu() if isinstance(points, torch.Tensor) else points,
                        dtype=np.float64).reshape(-1, 3)
    if len(points) >= 2:
        distances, _ = cKDTree(points).query(points, k=2)
        positive = distances[:, 1][distances[:, 1] > 0]
        if positive.size:
            return float(np.median(positive))
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) if len(points) else 0.0
    return 0.01 * diagonal if diagonal > 0 else 0.01


def voxelise(points: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """[A, 3] centres of the voxels of edge ``voxel_size`` that hold at least one of ``points`` [P, 3]:
    ``round(p / voxel_size) * voxel_size``, each voxel once, in lexicographic order of its index."""
    keys = torch.round(points.detach().to(torch.float64) / voxel_size).to(torch.int64)
    return (torch.unique(keys, dim=0).to(torch.float64) * voxel_size).to(points.dtype)


# --- decoding ------------------------------------------------------------------------------
def _mlp(inputs: int, hidden: int, outputs: int, generator: torch.Generator) -> nn.Sequential:
    """Linear -> ReLU -> Linear, weights and biases uniform in ±1/sqrt(fan_in) drawn from ``generator``."""
    layers = nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, outputs))
    with torch.no_grad():
        for layer in (layers[0], layers[2]):
            bound = 1.0 / math.sqrt(layer.in_features)
            layer.weight.uniform_(-bound, bound, generator=generator)
            layer.bias.uniform_(-bound, bound, generator=generator)
    return layers


class ScaffoldDecoder(nn.Module):
    """The three MLPs that turn an anchor's feature and its view into its ``k`` neural Gaussians.

    Input per anchor: ``[feature (F), unit direction camera -> anchor (3), distance / extent (1)]``.
    """

    def __init__(self, feature_dim: int, offsets: int, *, seed: int = 0):
        super().__init__()
        generator = torch.Generator().manual_seed(seed)
        inputs = feature_dim + 4
        self.offsets = offsets
        self.opacity = _mlp(inputs, feature_dim, offsets, generator)
        self.colour = _mlp(inputs, feature_dim, 3 * offsets, generator)
        self.covariance = _mlp(inputs, feature_dim, 7 * offsets, generator)

    def forward(self, features: torch.Tensor, directions: torch.Tensor,
                distances: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """features [A, F], directions [A, 3] (unit), distances [A, 1] ->
        opacity [A, k] in (-1, 1), colour [A, k, 3] in (0, 1), scale factors [A, k, 3] in (0, 1),
        quaternions [A, k, 4] (unit, wxyz)."""
        inputs = torch.cat([features, directions, distances], dim=-1)
        count, k = features.shape[0], self.offsets
        opacity = torch.tanh(self.opacity(inputs))
        colour = torch.sigmoid(self.colour(inputs)).reshape(count, k, 3)
        covariance = self.covariance(inputs).reshape(count, k, 7)
        scale_factors = torch.sigmoid(covariance[..., :3])
        quats = nn.functional.normalize(covariance[..., 3:], dim=-1)
        return opacity, colour, scale_factors, quats


@dataclass
class Decoded:
    """Neural Gaussians of some anchors for one camera (or one camera per anchor).

    ``params``: what is rasterized (the kept Gaussians: opacity > 0; degree-0 SH colours);
    ``anchor_index`` [V]: the anchors decoded; ``slots`` [M]: ``anchor * k + offset`` of every
    kept Gaussian; ``opacity`` [V, k]: every decoded Gaussian's opacity (detached, may be < 0).
    """

    params: RenderParams
    anchor_index: torch.Tensor
    slots: torch.Tensor
    opacity: torch.Tensor


def camera_centre(viewmat: torch.Tensor) -> torch.Tensor:
    """[3] world position of a camera from its [4, 4] world-to-camera matrix."""
    rotation, translation = viewmat[:3, :3], viewmat[:3, 3]
    return -rotation.T @ translation


def decode_anchors(positions: torch.Tensor, features: torch.Tensor, offsets: torch.Tensor, log_scaling: torch.Tensor,
                   decoder: ScaffoldDecoder, camera_centres: torch.Tensor, *, extent: float = 1.0,
                   anchor_index: Optional[torch.Tensor] = None) -> Decoded:
    """Decode anchors into their neural Gaussians.

    positions [V, 3] (not differentiated), features [V, F], offsets [V, k, 3], log_scaling [V, 6],
    camera_centres [3] (one camera) or [V, 3] (one per anchor); ``extent``: the scene extent the
    distances are divided by; ``anchor_index`` [V]: the anchors' indices in the whole set (default
    0..V-1). Gaussians whose opacity is not positive are left out of ``params``; when none is
    positive, all are kept with opacity 0 (the render stays differentiable).
    """
    positions = positions.detach()
    count, k = offsets.shape[0], offsets.shape[1]
    if anchor_index is None:
        anchor_index = torch.arange(count, device=positions.device)
    relative = positions - camera_centres.to(positions)
    distance = relative.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    opacity, colour, scale_factors, quats = decoder(features, relative / distance, distance / extent)
    scaling = torch.exp(log_scaling)
    means = positions[:, None, :] + offsets * scaling[:, None, :3]
    scales = scaling[:, None, 3:] * scale_factors
    flat_opacity = opacity.reshape(-1)
    kept = flat_opacity > 0
    if not bool(kept.any()):
        kept = torch.ones_like(kept)
    slots = (anchor_index[:, None] * k + torch.arange(k, device=positions.device)).reshape(-1)[kept]
    params = RenderParams(means=means.reshape(-1, 3)[kept], quats=quats.reshape(-1, 4)[kept],
                          scales=scales.reshape(-1, 3)[kept], opacities=flat_opacity[kept].clamp_min(0.0),
                          colors=rgb_to_sh_dc(colour.reshape(-1, 3)[kept])[:, None, :], sh_degree=0)
    return Decoded(params=params, anchor_index=anchor_index, slots=slots, opacity=opacity.detach())


def visible_anchors(positions: torch.Tensor, offsets: torch.Tensor, log_scaling: torch.Tensor, viewmat: torch.Tensor,
                    K: torch.Tensor, width: int, height: int, *, near_plane: float = NEAR_PLANE) -> torch.Tensor:
    """[A] bool: anchors whose neural Gaussians may reach the image.

    An anchor is a sphere around its centre of radius = its farthest offset plus three times its
    largest Gaussian scale; it is visible when its centre is in front of the camera and the
    sphere's projection (radius max(fx, fy) * r / z pixels) overlaps the image.
    """
    with torch.no_grad():
        scaling = torch.exp(log_scaling)
        radius = (offsets * scaling[:, None, :3]).norm(dim=-1).amax(dim=1) + 3.0 * scaling[:, 3:].amax(dim=1)
        u, v, z, in_front = project_points(positions, viewmat, K, near_plane=near_plane)
        K = K.to(positions)
        pixels = torch.maximum(K[0, 0], K[1, 1]) * radius / z
        return in_front & (u >= -pixels) & (u <= width + pixels) & (v >= -pixels) & (v <= height + pixels)


def volume_regulariser(scales: torch.Tensor) -> torch.Tensor:
    """Scaffold-GS's volume term: the mean over Gaussians of the product of their three scales
    (``scales`` [M, 3]; 0 for M = 0)."""
    if scales.shape[0] == 0:
        return scales.sum() * 0.0
    return scales.prod(dim=-1).mean()


# --- growing and pruning -------------------------------------------------------------------
@dataclass
class Growth:
    """New anchors: ``positions`` [G, 3] (voxel centres), ``voxel_sizes`` [G] (their level's voxel
    edge), and the neural Gaussians that asked for them: ``members`` [C] (flat ``anchor * k +
    offset`` slots) with ``member_anchor`` [C] the new anchor (0..G-1) each one falls into."""

    positions: torch.Tensor
    voxel_sizes: torch.Tensor
    members: torch.Tensor
    member_anchor: torch.Tensor


def grow_anchors(anchor_positions: torch.Tensor, gaussian_positions: torch.Tensor, mean_gradients: torch.Tensor,
                 observed: torch.Tensor, *, voxel_size: float, threshold: float, levels: int,
                 generator: Optional[torch.Generator] = None) -> Growth:
    """New anchors where neural Gaussians with large gradients lie in voxels without an anchor.

    anchor_positions [A, 3]; gaussian_positions [A*k, 3]; mean_gradients [A*k] (mean NDC gradient
    norm while visible); observed [A*k] bool (seen often enough to be judged). For level m of
    ``levels`` (0 = coarsest) the voxel edge is ``voxel_size * 4^(levels-1-m)`` and a Gaussian is
    significant when observed and its mean gradient is at least ``threshold * 2^m``; the voxels of
    significant Gaussians that hold no anchor (existing ones, or grown at a coarser level) get one
    at their centre. With a ``generator`` each such voxel of level m survives with probability
    1 - 0.5^(m+1) (the paper's random elimination against explosive growth); None keeps all.
    """
    device, dtype = anchor_positions.device, anchor_positions.dtype
    existing = anchor_positions.detach()
    positions, sizes, members, member_anchor = [], [], [], []
    grown = 0
    for level in range(levels):
        size = voxel_size * LEVEL_SIZE_FACTOR ** (levels - 1 - level)
        significant = observed & (mean_gradients >= threshold * LEVEL_THRESHOLD_FACTOR ** level)
        candidates = torch.nonzero(significant).reshape(-1)
        if candidates.numel() == 0:
            continue
        occupied_keys = torch.round(existing.to(torch.float64) / size).to(torch.int64)
        candidate_keys = torch.round(gaussian_positions[candidates].detach().to(torch.float64) / size).to(torch.int64)
        keys, inverse = torch.unique(torch.cat([occupied_keys, candidate_keys]), dim=0, return_inverse=True)
        occupied = torch.zeros(len(keys), dtype=torch.bool, device=device)
        occupied[inverse[:len(occupied_keys)]] = True
        candidate_voxel = inverse[len(occupied_keys):]
        free = ~occupied[candidate_voxel]
        new_voxels = torch.unique(candidate_voxel[free])
        if generator is not None and new_voxels.numel():
            draw = torch.rand(new_voxels.numel(), generator=generator, device=generator.device).to(device)
            new_voxels = new_voxels[draw > 0.5 ** (level + 1)]
        if new_voxels.numel() == 0:
            continue
        # number the level's new voxels 0..n-1 and keep the candidates that fall into one
        number = torch.full((len(keys),), -1, dtype=torch.int64, device=device)
        number[new_voxels] = torch.arange(new_voxels.numel(), device=device)
        member_number = number[candidate_voxel]
        joined = member_number >= 0
        centres = (keys[new_voxels].to(torch.float64) * size).to(dtype)
        positions.append(centres)
        sizes.append(torch.full((len(centres),), size, dtype=dtype, device=device))
        members.append(candidates[joined])
        member_anchor.append(member_number[joined] + grown)
        grown += len(centres)
        existing = torch.cat([existing, centres])
    if not positions:
        empty = torch.zeros(0, dtype=torch.int64, device=device)
        return Growth(torch.zeros(0, 3, dtype=dtype, device=device), torch.zeros(0, dtype=dtype, device=device),
                      empty, empty)
    return Growth(torch.cat(positions), torch.cat(sizes), torch.cat(members), torch.cat(member_anchor))


def prune_anchors(opacity_accum: torch.Tensor, visits: torch.Tensor, *, min_opacity: float,
                  min_visits: float) -> torch.Tensor:
    """[A] bool: anchors to remove. An anchor seen in more than ``min_visits`` steps is pruned when its
    neural Gaussians' opacities (negative ones counted as 0), summed over its Gaussians and steps,
    average below ``min_opacity`` per step."""
    return (visits > min_visits) & (opacity_accum < min_opacity * visits)


# --- the strategy: anchors, their statistics, growing and pruning ---------------------------
class ScaffoldStrategy(Strategy):
    """Scaffold-GS's anchor set and its adaptive control (replaces the trainer's clone/split/prune).

    ``prepare_initial`` turns the initial Gaussians (the SfM points) into anchors at the centres of
    their voxels; ``setup`` adds the per-anchor features [A, F], offsets [A, k, 3] and log scalings
    [A, 6] to the optimizer as per-Gaussian groups. Statistics are gathered from
    ``scaffold_statistics_from`` until the run's ``densify_until`` (scaled steps); anchors are grown
    (:func:`grow_anchors`) and pruned (:func:`prune_anchors`) every ``densify_every`` steps after
    ``scaffold_grow_from``. ``last`` is the :class:`Decoded` of the step's render (set by the hook).
    """

    name = "scaffold-gs"

    def __init__(self, settings: ScaffoldGSConfig, config: Any):
        self.settings = settings
        self.schedule = config.schedule()
        self.iterations = int(config.iterations)
        self.statistics_from = config.scaled_step(settings.scaffold_statistics_from)
        self.grow_from = config.scaled_step(settings.scaffold_grow_from)
        self.max_anchors = max(1, int(config.max_gaussians) // settings.scaffold_offsets)
        self.voxel_size = float(settings.scaffold_voxel_size)
        self.last: Optional[Decoded] = None
        self.features: Optional[nn.Parameter] = None
        self.offsets: Optional[nn.Parameter] = None
        self.log_scaling: Optional[nn.Parameter] = None

    # --- anchors ---------------------------------------------------------------------
    def prepare_initial(self, gaussians: GaussianModel) -> None:
        points = gaussians.params["means"].detach()
        if self.voxel_size <= 0:
            self.voxel_size = voxel_size_from_points(points)
        centres = voxelise(points, self.voxel_size).cpu().numpy()
        anchors = GaussianModel.from_points(centres, np.full_like(centres, 0.5), max_sh_degree=gaussians.max_sh_degree)
        gaussians.params = anchors.params

    def setup(self, context: StrategyContext) -> None:
        super().setup(context)
        settings, gaussians = self.settings, context.gaussians
        count, device = len(gaussians), context.device
        # the anchors' scaling starts at their spacing (from_points: mean distance to 3 neighbours)
        log_spacing = gaussians.params["log_scales"].detach()[:, :1]
        self.features = nn.Parameter(torch.zeros(count, settings.scaffold_feature_dim, device=device))
        self.offsets = nn.Parameter(torch.zeros(count, settings.scaffold_offsets, 3, device=device))
        self.log_scaling = nn.Parameter(log_spacing.repeat(1, 6).contiguous())
        optimizer = context.optimizer
        optimizer.add_group("scaffold_features", self.features, FEATURE_LR, per_gaussian=True)
        offset_lr = ExponentialDecay(*OFFSET_LR, max_steps=self.iterations)
        optimizer.add_group("scaffold_offsets", self.offsets, offset_lr(0), schedule=offset_lr, per_gaussian=True)
        optimizer.add_group("scaffold_log_scaling", self.log_scaling, SCALING_LR, per_gaussian=True)
        self._zero_statistics(count)
        context.message(f"Scaffold-GS: {count} anchors on voxels of {self.voxel_size:.4g} scene units, "
                        f"{settings.scaffold_offsets} neural Gaussians each")

    def _zero_statistics(self, count: int) -> None:
        device, k = self.context.device, self.settings.scaffold_offsets
        self.gradient_accum = torch.zeros(count * k, device=device)
        self.gaussian_visits = torch.zeros(count * k, device=device)
        self.opacity_accum = torch.zeros(count, device=device)
        self.anchor_visits = torch.zeros(count, device=device)

    def gaussian_positions(self) -> torch.Tensor:
        """[A*k, 3] the neural Gaussians' centres (detached)."""
        with torch.no_grad():
            positions = self.context.gaussians.params["means"]
            scaling = torch.exp(self.log_scaling[:, None, :3])
            return (positions[:, None, :] + self.offsets * scaling).reshape(-1, 3)

    # --- statistics --------------------------------------------------------------------
    def gathers_statistics(self, step: int) -> bool:
        return self.statistics_from <= step < self.schedule.densify_until

    def step_post_backward(self, step: int, view: Any, output: Any) -> None:
        decoded = self.last
        means2d = output.meta.get("means2d")
        if decoded is None or not self.gathers_statistics(step) or means2d is None \
                or means2d.shape[1] != decoded.slots.numel():
            return
        gradient = output.meta.get("densify_grad", means2d.grad)
        if gradient is None:
            return
        with torch.no_grad():
            scale = torch.tensor([0.5 * view.width, 0.5 * view.height], dtype=gradient.dtype, device=gradient.device)
            norms = (gradient[0] * scale).norm(dim=-1)  # NDC units, as the default strategy's
            radii = output.meta["radii"][0]
            if radii.dim() == 2:
                radii = radii.max(dim=-1).values
            visible = (radii > 0).to(norms.dtype)
            slots = decoded.slots.to(norms.device)
            self.gradient_accum.index_add_(0, slots, norms * visible)
            self.gaussian_visits.index_add_(0, slots, visible)
            index = decoded.anchor_index.to(norms.device)
            self.opacity_accum.index_add_(0, index, decoded.opacity.clamp_min(0.0).sum(dim=1).to(norms.dtype))
            self.anchor_visits.index_add_(0, index, torch.ones_like(index, dtype=norms.dtype))

    # --- growing and pruning -------------------------------------------------------------
    def is_update_step(self, step: int) -> bool:
        return self.grow_from < step < self.schedule.densify_until and step % self.schedule.densify_every == 0

    def step_post_optimizer(self, step: int) -> list[DensifyReport]:
        if not self.is_update_step(step):
            return []
        return [self.update(step)]

    def update(self, step: int) -> DensifyReport:
        """Grow anchors from the gathered statistics, then prune; reset the judged statistics."""
        settings, context = self.settings, self.context
        gaussians, device = context.gaussians, context.device
        k = settings.scaffold_offsets
        every = self.schedule.densify_every
        before = len(gaussians)
        self.last = None
        with torch.no_grad():
            mean_gradients = self.gradient_accum / self.gaussian_visits.clamp_min(1.0)
            observed = self.gaussian_visits > 0.5 * settings.scaffold_success_threshold * every
            growth = grow_anchors(gaussians.params["means"], self.gaussian_positions(), mean_gradients, observed,
                                  voxel_size=self.voxel_size, threshold=settings.scaffold_grow_threshold,
                                  levels=settings.scaffold_grow_levels, generator=context.generator)
            room = max(0, self.max_anchors - before)
            grown = min(len(growth.positions), room)
            capped = grown < len(growth.positions)
            self.gradient_accum[observed] = 0.0
            self.gaussian_visits[observed] = 0.0
            parents = torch.zeros(0, dtype=torch.int64, device=device)
            if grown:
                parents = self._append(growth, grown)
            # prune (grown anchors have not been seen yet, so they stay)
            judged = self.anchor_visits > settings.scaffold_success_threshold * every
            prune = prune_anchors(self.opacity_accum, self.anchor_visits, min_opacity=settings.scaffold_prune_opacity,
                                  min_visits=settings.scaffold_success_threshold * every)
            self.opacity_accum[judged] = 0.0
            self.anchor_visits[judged] = 0.0
            if bool(prune.all()):
                prune = torch.zeros_like(prune)  # never an empty model
            source = torch.cat([torch.arange(before, device=device), parents])
            keep = ~prune
            if bool(prune.any()):
                self._select(keep)
            source = source[keep]
        if capped:
            context.message(f"warning: Scaffold-GS anchor growth capped at {self.max_anchors} anchors "
                            f"(max_gaussians / {k})")
        report = DensifyReport(step=step, count_before=before, count_after=len(gaussians), cloned=grown,
                               pruned=int(prune.sum()), capped=capped, source_index=source)
        context.message(f"Scaffold-GS step {step}: {before} -> {len(gaussians)} anchors "
                        f"(+{grown} grown, -{report.pruned} pruned)")
        return report

    def _append(self, growth: Growth, count: int) -> torch.Tensor:
        """Add the first ``count`` anchors of ``growth``; returns each one's parent anchor [count]."""
        context, settings = self.context, self.settings
        gaussians, optimizer, device = context.gaussians, context.optimizer, context.device
        k, before = settings.scaffold_offsets, len(gaussians)
        positions = growth.positions[:count].to(device)
        log_size = torch.log(growth.voxel_sizes[:count].to(device))
        joined = growth.member_anchor < count
        members, member_anchor = growth.members[joined], growth.member_anchor[joined]
        member_parent = torch.div(members, k, rounding_mode="floor")
        # a new anchor's feature: the mean feature of the anchors whose Gaussians asked for it
        features = torch.zeros(count, self.features.shape[1], device=device)
        features.index_add_(0, member_anchor, self.features.detach()[member_parent])
        counts = torch.zeros(count, device=device).index_add_(0, member_anchor, torch.ones_like(member_anchor,
                                                                                              dtype=features.dtype))
        features /= counts.clamp_min(1.0)[:, None]
        parents = torch.zeros(count, dtype=torch.int64, device=device)
        parents[member_anchor] = member_parent  # any one of them
        sh_rest = gaussians.params["sh_rest"]
        rows = {
            "means": positions,
            "sh_dc": torch.zeros(count, 1, 3, device=device),
            "sh_rest": torch.zeros((count,) + tuple(sh_rest.shape[1:]), device=device),
            "opacity_logit": torch.zeros(count, device=device),
            "log_scales": log_size[:, None].repeat(1, 3),
            "quats": torch.tensor([1.0, 0.0, 0.0, 0.0], device=device).repeat(count, 1),
            "scaffold_features": features,
            "scaffold_offsets": torch.zeros(count, k, 3, device=device),
            "scaffold_log_scaling": log_size[:, None].repeat(1, 6),
        }
        self._adopt(optimizer.append(rows))
        self.gradient_accum = torch.cat([self.gradient_accum, torch.zeros(count * k, device=device)])
        self.gaussian_visits = torch.cat([self.gaussian_visits, torch.zeros(count * k, device=device)])
        self.opacity_accum = torch.cat([self.opacity_accum, torch.zeros(count, device=device)])
        self.anchor_visits = torch.cat([self.anchor_visits, torch.zeros(count, device=device)])
        assert len(gaussians) == before + count
        return parents

    def _select(self, keep: torch.Tensor) -> None:
        k = self.settings.scaffold_offsets
        self._adopt(self.context.optimizer.select(keep))
        slot_keep = keep[:, None].expand(-1, k).reshape(-1)
        self.gradient_accum = self.gradient_accum[slot_keep]
        self.gaussian_visits = self.gaussian_visits[slot_keep]
        self.opacity_accum = self.opacity_accum[keep]
        self.anchor_visits = self.anchor_visits[keep]

    def _adopt(self, params: dict[str, nn.Parameter]) -> None:
        """Take the optimizer's new tensors into the Gaussian model and the anchor attributes."""
        self.context.gaussians.set_params({name: params[name] for name in PARAMETER_NAMES})
        self.features = params["scaffold_features"]
        self.offsets = params["scaffold_offsets"]
        self.log_scaling = params["scaffold_log_scaling"]

    # --- checkpoints -------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"voxel_size": self.voxel_size,
                "features": self.features.detach().cpu().clone(), "offsets": self.offsets.detach().cpu().clone(),
                "log_scaling": self.log_scaling.detach().cpu().clone(),
                "gradient_accum": self.gradient_accum.cpu(), "gaussian_visits": self.gaussian_visits.cpu(),
                "opacity_accum": self.opacity_accum.cpu(), "anchor_visits": self.anchor_visits.cpu()}

    def load_state_dict(self, state: dict) -> None:
        if not state:
            return
        from ...errors import CheckpointError

        if tuple(state["features"].shape) != tuple(self.features.shape) or \
                tuple(state["offsets"].shape) != tuple(self.offsets.shape):
            raise CheckpointError(f"the checkpoint's Scaffold-GS anchors have shape {tuple(state['offsets'].shape)}, "
                                  f"this run's {tuple(self.offsets.shape)}",
                                  hint="resume with the run's own settings (esgs train reads them from config.json)")
        device = self.context.device
        self.voxel_size = float(state["voxel_size"])
        with torch.no_grad():
            self.features.copy_(state["features"])
            self.offsets.copy_(state["offsets"])
            self.log_scaling.copy_(state["log_scaling"])
        self.gradient_accum = state["gradient_accum"].to(device)
        self.gaussian_visits = state["gaussian_visits"].to(device)
        self.opacity_accum = state["opacity_accum"].to(device)
        self.anchor_visits = state["anchor_visits"].to(device)


# --- the hook: MLPs, decoding, the volume term, export ---------------------------------------
class ScaffoldHook(TrainHook):
    """Decodes the anchors of :class:`ScaffoldStrategy` into the Gaussians every render uses."""

    name = "scaffold_gs"

    def __init__(self, settings: ScaffoldGSConfig, strategy: ScaffoldStrategy, iterations: int):
        self.settings = settings
        self.strategy = strategy
        self.iterations = int(iterations)
        self.decoder: Optional[ScaffoldDecoder] = None
        self.camera_centres: Optional[torch.Tensor] = None

    def setup(self, run: RunView) -> None:
        settings = self.settings
        self.decoder = ScaffoldDecoder(settings.scaffold_feature_dim, settings.scaffold_offsets,
                                       seed=run.seed).to(run.device)
        for name, module, rates in (("opacity", self.decoder.opacity, OPACITY_MLP_LR),
                                    ("colour", self.decoder.colour, COLOUR_MLP_LR),
                                    ("covariance", self.decoder.covariance, COVARIANCE_MLP_LR)):
            schedule = ExponentialDecay(*rates, max_steps=self.iterations)
            run.add_parameter_group(f"scaffold_mlp_{name}", list(module.parameters()), schedule(0), schedule=schedule)
        views = run.train_views or run.test_views
        self.camera_centres = torch.stack([camera_centre(view.viewmat.to(torch.float32)) for view in views]).to(run.device)
        if settings.scaffold_volume_weight > 0:
            run.add_loss_term(LossTerm("scaffold_volume", settings.scaffold_volume_weight, _volume_term))

    @property
    def extent(self) -> float:
        return max(float(self.strategy.context.extent), 1e-6)

    def decode_view(self, run: RunView, view: Any) -> Decoded:
        """The neural Gaussians of the anchors in ``view`` (differentiable in the anchors' tensors and the MLPs)."""
        strategy = self.strategy
        positions = run.gaussians.params["means"].detach()
        visible = visible_anchors(positions, strategy.offsets, strategy.log_scaling, view.viewmat, view.K,
                                  view.width, view.height)
        if not bool(visible.any()):
            visible = torch.ones_like(visible)
        index = torch.nonzero(visible).reshape(-1)
        centre = camera_centre(view.viewmat.to(positions))
        return decode_anchors(positions[index], strategy.features[index], strategy.offsets[index],
                              strategy.log_scaling[index], self.decoder, centre, extent=self.extent,
                              anchor_index=index)

    def decode_reference(self, run: RunView) -> Decoded:
        """Every anchor decoded for its nearest training camera (the exported, view-independent model)."""
        strategy = self.strategy
        positions = run.gaussians.params["means"].detach()
        nearest = torch.cdist(positions, self.camera_centres.to(positions)).argmin(dim=1)
        return decode_anchors(positions, strategy.features, strategy.offsets, strategy.log_scaling, self.decoder,
                              self.camera_centres.to(positions)[nearest], extent=self.extent)

    def before_render(self, run: RunView, context: StepContext, params: RenderParams) -> RenderParams:
        decoded = self.decode_view(run, context.view)
        self.strategy.last = decoded
        context.extras["scaffold_neural_gaussians"] = decoded.slots.numel()
        return decoded.params

    def model_params(self, run: RunView, params: RenderParams) -> RenderParams:
        with torch.no_grad():
            return self.decode_reference(run).params

    def view_params(self, run: RunView, view: Any, params: RenderParams) -> RenderParams:
        with torch.no_grad():
            return self.decode_view(run, view).params

    def export_model(self, run: RunView, gaussians: GaussianModel) -> GaussianModel:
        with torch.no_grad():
            return decoded_model(self.decode_reference(run).params, gaussians.max_sh_degree)

    def state_dict(self) -> dict:
        return {"decoder": {name: value.detach().cpu().clone() for name, value in self.decoder.state_dict().items()}}

    def load_state_dict(self, state: dict) -> None:
        if state.get("decoder"):
            self.decoder.load_state_dict(state["decoder"])


def _volume_term(context: LossContext) -> torch.Tensor:
    return volume_regulariser(context.params.scales)


def decoded_model(params: RenderParams, max_sh_degree: int) -> GaussianModel:
    """Decoded neural Gaussians (degree-0 colours) as a :class:`GaussianModel` of degree
    ``max_sh_degree`` (higher bands 0), ready for a standard 3DGS PLY."""
    count = params.means.shape[0]
    eps = 1e-6
    rest = (max_sh_degree + 1) ** 2 - 1
    return GaussianModel.from_tensors(
        means=params.means, sh_dc=params.colors[:, :1, :], sh_rest=torch.zeros(count, rest, 3, device=params.means.device, dtype=params.means.dtype),
        opacity_logit=inverse_sigmoid(params.opacities.clamp(eps, 1.0 - eps)),
        log_scales=torch.log(params.scales.clamp_min(1e-12)), quats=params.quats, max_sh_degree=max_sh_degree)


def scaffold_parts(settings: ScaffoldGSConfig, config: Any):
    """The :class:`~esgs.core.train.method.MethodParts` of a Scaffold-GS run."""
    from ...train.method import MethodParts

    settings.validate()
    strategy = ScaffoldStrategy(settings, config)
    return MethodParts(hooks=[ScaffoldHook(settings, strategy, config.iterations)], strategy=strategy)
