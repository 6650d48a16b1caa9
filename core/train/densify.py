"""Adaptive density control as in 3DGS: clone, split, prune, opacity reset.

Gradient units. 3DGS thresholds (``densify_grad_threshold = 2e-4``) the mean norm of the
loss gradient with respect to each Gaussian's projected centre in *NDC* units (x, y in
[-1, 1]). Our rasterizer reports ``means2d`` in pixels, and ``x_pixel = (x_ndc + 1) W / 2
- 0.5``, so ``dL/dx_ndc = dL/dx_pixel * W / 2`` (and ``H / 2`` for y). :meth:`DensifyState.accumulate`
applies that factor per axis, so the paper's threshold keeps its meaning at any resolution.

After every clone/split/prune the statistics restart from zero, as in 3DGS.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Optional

import torch

from ..render.projection import quaternion_to_matrix
from .gaussians import GaussianModel
from .optim import TrainOptimizer


@dataclass
class DensifyState:
    """Statistics gathered between densifications, one entry per Gaussian.

    ``grad_accum`` [N]: summed NDC gradient norms; ``visible_count`` [N]: steps in which the
    Gaussian was visible; ``max_radii`` [N]: largest screen radius seen (pixels).
    """

    grad_accum: torch.Tensor
    visible_count: torch.Tensor
    max_radii: torch.Tensor
    warned_cap: bool = False

    @staticmethod
    def zeros(count: int, device: torch.device | str = "cpu") -> "DensifyState":
        return DensifyState(torch.zeros(count, device=device), torch.zeros(count, device=device),
                            torch.zeros(count, device=device))

    def reset(self, count: int) -> None:
        device = self.grad_accum.device
        self.grad_accum = torch.zeros(count, device=device)
        self.visible_count = torch.zeros(count, device=device)
        self.max_radii = torch.zeros(count, device=device)

    def accumulate(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> None:
        """Add one step's statistics.

        means2d_grad: [C, N, 2] gradient w.r.t. pixel coordinates; radii: [C, N] (0 = not
        visible). Each camera of the batch counts as one observation.
        """
        scale = torch.tensor([0.5 * width, 0.5 * height], dtype=means2d_grad.dtype, device=means2d_grad.device)
        norms = (means2d_grad * scale).norm(dim=-1)  # [C, N] in NDC units
        radii = radii.to(self.max_radii.dtype)
        if radii.dim() == 3:  # some backends give per-axis radii [C, N, 2]
            radii = radii.max(dim=-1).values
        visible = radii > 0
        self.grad_accum += (norms * visible).sum(dim=0)
        self.visible_count += visible.sum(dim=0).to(self.visible_count.dtype)
        self.max_radii = torch.maximum(self.max_radii, radii.max(dim=0).values)

    def mean_gradients(self) -> torch.Tensor:
        """[N] mean NDC gradient norm over the steps each Gaussian was visible (0 if never)."""
        return torch.where(self.visible_count > 0, self.grad_accum / self.visible_count.clamp_min(1),
                           torch.zeros_like(self.grad_accum))

    def select(self, keep: torch.Tensor) -> None:
        self.grad_accum = self.grad_accum[keep]
        self.visible_count = self.visible_count[keep]
        self.max_radii = self.max_radii[keep]

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum.cpu(), "visible_count": self.visible_count.cpu(),
                "max_radii": self.max_radii.cpu(), "warned_cap": self.warned_cap}

    def load_state_dict(self, state: dict) -> None:
        device = self.grad_accum.device
        self.grad_accum = state["grad_accum"].to(device)
        self.visible_count = state["visible_count"].to(device)
        self.max_radii = state["max_radii"].to(device)
        self.warned_cap = bool(state["warned_cap"])


@dataclass
class DensifyReport:
    """What one densification did. ``source_index`` [N_after] names, for every Gaussian
    after the change, the Gaussian before it that it came from (modules with per-Gaussian
    state remap it with ``state[source_index]``)."""

    step: int
    count_before: int
    count_after: int
    cloned: int = 0
    split: int = 0
    pruned: int = 0
    capped: bool = False
    reset_opacity: bool = False
    source_index: Optional[torch.Tensor] = field(default=None, repr=False)


@dataclass(frozen=True)
class DensifySettings:
    """Thresholds of one densification (see :class:`~esgs.core.train.config.TrainConfig`)."""

    grad_threshold: float
    percent_dense: float
    extent: float
    prune_opacity: float
    prune_large: bool
    max_screen_size_px: float
    max_world_size: float
    max_gaussians: int
    split_children: int = 2


def densify_and_prune(model: GaussianModel, optimizer: TrainOptimizer, state: DensifyState,
                      settings: DensifySettings, *, step: int, generator: torch.Generator) -> DensifyReport:
    """Clone small and split large high-gradient Gaussians, then prune, as 3DGS.

    - clone: mean NDC gradient >= threshold and largest scale <= percent_dense * extent:
      an identical copy is appended (the two then separate under the optimizer);
    - split: gradient >= threshold and larger than that: ``split_children`` children are
      sampled from the Gaussian (positions from its own distribution, scales divided by
      0.8 * children), the parent is removed;
    - prune: opacity < prune_opacity, and (after the first opacity reset) screen radius >
      max_screen_size_px or largest scale > max_world_size * extent.

    Growth is limited to ``max_gaussians``: the candidates with the largest gradients are
    kept and a single warning is issued the first time the cap bites.
    """
    count = len(model)
    grads = state.mean_gradients()
    with torch.no_grad():
        max_scale = model.scales().max(dim=1).values
        high = grads >= settings.grad_threshold
        small = max_scale <= settings.percent_dense * settings.extent
        clone_mask = high & small
        split_mask = high & ~small

        # the cap: each clone adds one Gaussian, each split adds children - 1
        children = settings.split_children
        room = max(settings.max_gaussians - count, 0)
        growth = int(clone_mask.sum()) + int(split_mask.sum()) * (children - 1)
        capped = growth > room
        if capped:
            clone_mask, split_mask = _limit_growth(grads, clone_mask, split_mask, room, children)
            if not state.warned_cap:
                state.warned_cap = True
                warnings.warn(f"max_gaussians = {settings.max_gaussians} reached at step {step}: "
                              "densification stops adding Gaussians (pruning continues)", RuntimeWarning, stacklevel=2)

        clone_index = clone_mask.nonzero().squeeze(1)
        split_index = split_mask.nonzero().squeeze(1)
        params = model.params
        new_rows = {name: params[name].detach()[clone_index] for name in params}

        if split_index.numel():
            parent_scales = model.scales()[split_index].repeat(children, 1)  # [S*c, 3]
            offsets = torch.normal(torch.zeros_like(parent_scales), parent_scales, generator=generator)
            rotations = quaternion_to_matrix(params["quats"].detach()[split_index]).repeat(children, 1, 1)
            child_means = torch.bmm(rotations, offsets[:, :, None])[:, :, 0] + params["means"].detach()[split_index].repeat(children, 1)
            split_rows = {name: params[name].detach()[split_index].repeat(
                (children,) + (1,) * (params[name].dim() - 1)) for name in params}
            split_rows["means"] = child_means
            split_rows["log_scales"] = torch.log(parent_scales / (0.8 * children))
            new_rows = {name: torch.cat([new_rows[name], split_rows[name]], dim=0) for name in params}
        source_index = torch.cat([torch.arange(count, device=grads.device), clone_index, split_index.repeat(children)])

        # the split parents go; then opacity and size pruning over the old and the new rows,
        # decided before any parameter is rebuilt so that each is rebuilt once
        total = int(source_index.numel())
        remove = torch.zeros(total, dtype=torch.bool, device=grads.device)
        remove[split_index] = True
        remove |= torch.sigmoid(torch.cat([params["opacity_logit"].detach(), new_rows["opacity_logit"]])) \
            < settings.prune_opacity
        if settings.prune_large:
            max_radii = torch.cat([state.max_radii, torch.zeros(total - count, device=grads.device)])
            remove |= max_radii > settings.max_screen_size_px
            log_scales = torch.cat([params["log_scales"].detach(), new_rows["log_scales"]])
            remove |= torch.exp(log_scales).max(dim=1).values > settings.max_world_size * settings.extent
        keep = ~remove
        keep_new = keep[count:]
        kept_rows = {name: rows[keep_new] for name, rows in new_rows.items()}
        del new_rows, params  # the model's dict takes each new parameter as it is built
        optimizer.keep_and_append(keep[:count], kept_rows, into=model.params)
        source_index = source_index[keep]
        state.reset(len(model))
    pruned = int(remove.sum()) - int(split_index.numel())
    return DensifyReport(step=step, count_before=count, count_after=len(model), cloned=int(clone_index.numel()),
                         split=int(split_index.numel()), pruned=pruned, capped=capped, source_index=source_index)


def _limit_growth(grads: torch.Tensor, clone_mask: torch.Tensor, split_mask: torch.Tensor, room: int,
                  children: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Keep the highest-gradient candidates whose growth fits in ``room``."""
    candidates = (clone_mask | split_mask).nonzero().squeeze(1)
    order = candidates[torch.argsort(grads[candidates], descending=True, stable=True)]
    cost = torch.where(split_mask[order], children - 1, 1)
    fits = torch.cumsum(cost, dim=0) <= room
    chosen = torch.zeros_like(clone_mask)
    chosen[order[fits]] = True
    return clone_mask & chosen, split_mask & chosen


def reset_opacity(model: GaussianModel, optimizer: TrainOptimizer, value: float) -> None:
    """Clamp every opacity to at most ``value`` and zero its Adam moments (3DGS's reset)."""
    with torch.no_grad():
        clamped = torch.minimum(model.opacities(), torch.full_like(model.opacities(), value))
        logits = torch.log(clamped / (1.0 - clamped))
    model.set_params({"opacity_logit": optimizer.reset("opacity_logit", logits)})
