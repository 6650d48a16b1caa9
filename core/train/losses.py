"""Training losses as a list of named, weighted terms with start (and end) steps.

The 3DGS baseline is ``(1 - lambda) L1 + lambda (1 - SSIM)`` (:func:`photometric_terms`).
ESGS modules append their own :class:`LossTerm` (depth prior, normal prior...) from a
hook's ``setup``; a term that needs depth or normal maps says so in ``needs`` and the
trainer renders those channels only on the steps where such a term is active.

Masks: ``mask`` (False = sky or no surface, from the scene's mask source) never removes a
pixel from the photometric terms: every pixel is fitted, the sky by the run's sky model
(:mod:`.sky`). Masks keep the prior losses off the sky, and the ``sky_alpha`` term uses
them to keep Gaussians from painting it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import torch

from .fused_ssim import dssim


@dataclass
class LossContext:
    """Everything a loss term may look at for one step.

    image: [H, W, 3] rendered colour; target: [H, W, 3] ground truth in [0, 1]; mask:
    [H, W, 1] bool (True = valid) or None; alpha: [H, W, 1]; depth: [H, W, 1] or None;
    normals: [H, W, 3] or None (camera frame); view: the :class:`~.dataset.View`;
    output: the :class:`~.rendering.RenderOutput`; params: the
    :class:`~.gaussians.RenderParams` that were rendered; run: the run as hooks see it
    (:class:`~.hooks.RunView`), for terms that need scene-level data.
    """

    step: int
    image: torch.Tensor
    target: torch.Tensor
    mask: Optional[torch.Tensor]
    alpha: torch.Tensor
    depth: Optional[torch.Tensor] = None
    normals: Optional[torch.Tensor] = None
    view: Any = None
    output: Any = None
    params: Any = None
    run: Any = None
    cache: dict = field(default_factory=dict)



LossFunction = Callable[[LossContext], torch.Tensor]


@dataclass
class LossTerm:
    """A named loss term ``weight * function(context)``, active for start_step <= step < end_step.

    ``needs``: render channels the term reads ("depth", "normals"). Step numbers are
    this run's steps (scale 30,000-step values with ``TrainConfig.scaled_step``).
    ``densifies``: whether the term's screen-space gradient counts towards the clone/split
    statistic (``TrainConfig.densify_gradient = "photometric"`` leaves out the terms that say
    False: prior losses pull Gaussians towards a surface, which says nothing about where the
    images lack detail).
    """

    name: str
    weight: float
    function: LossFunction
    start_step: int = 0
    end_step: Optional[int] = None
    needs: frozenset = frozenset()
    densifies: bool = True

    def active(self, step: int) -> bool:
        return self.weight != 0.0 and step >= self.start_step and (self.end_step is None or step < self.end_step)


def l1_loss(context: LossContext) -> torch.Tensor:
    """Mean absolute colour error over every pixel (sky included: masks keep priors off the sky,
    never the photometric loss; the sky model learns it)."""
    return (context.image - context.target).abs().mean()


def dssim_loss(context: LossContext) -> torch.Tensor:
    """1 - SSIM (11x11 Gaussian window, 3DGS convention; see :mod:`esgs.core.metrics.image`);
    on the CPU one node over Numba kernels (:mod:`.fused_ssim`)."""
    return dssim(context.image, context.target)


def flattening_loss(scales: torch.Tensor, extent: float = 1.0) -> torch.Tensor:
    """Mean over Gaussians of the smallest scale, as a fraction of ``extent``. scales: [N, 3].

    Flattens the Gaussians into discs, so that each one's shortest axis is a surface normal
    (PGSR's flattening term; ESGS's ``flatten_weight``)."""
    if scales.shape[0] == 0:
        return scales.sum() * 0.0
    return scales.min(dim=-1).values.mean() / float(extent)


def photometric_terms(lambda_dssim: float) -> list[LossTerm]:
    """The 3DGS photometric loss as two terms: "l1" (1 - lambda) and "dssim" (lambda)."""
    return [LossTerm("l1", 1.0 - lambda_dssim, l1_loss), LossTerm("dssim", lambda_dssim, dssim_loss)]


def needed_channels(terms: list[LossTerm], step: int) -> set[str]:
    """Union of ``needs`` of the terms active at ``step``."""
    needs: set[str] = set()
    for term in terms:
        if term.active(step):
            needs |= set(term.needs)
    return needs


@dataclass
class LossParts:
    """The step's loss split by :attr:`LossTerm.densifies`: ``densifying`` and ``other`` are the
    weighted sums of each group (None when the group has no active term); ``values`` each
    active term's unweighted value (for logging); ``total_value`` the total as a float."""

    densifying: Optional[torch.Tensor]
    other: Optional[torch.Tensor]
    values: dict[str, float]
    total_value: float = float("nan")

    @property
    def total(self) -> torch.Tensor:
        parts = [part for part in (self.densifying, self.other) if part is not None]
        return parts[0] if len(parts) == 1 else parts[0] + parts[1]


def loss_parts(terms: list[LossTerm], context: LossContext) -> LossParts:
    """Evaluate the active terms once, summed per group (see :class:`LossParts`)."""
    sums: dict[bool, Optional[torch.Tensor]] = {True: None, False: None}
    names: list[str] = []
    detached: list[torch.Tensor] = []
    for term in terms:
        if not term.active(context.step):
            continue
        value = term.function(context)
        names.append(term.name)
        detached.append(value.detach().reshape(()))
        weighted = term.weight * value
        sums[term.densifies] = weighted if sums[term.densifies] is None else sums[term.densifies] + weighted
    if sums[True] is None and sums[False] is None:
        sums[True] = context.image.sum() * 0.0
    parts = LossParts(densifying=sums[True], other=sums[False], values={})
    # every value reaches the host in one copy: on a GPU each float() is a wait for the device
    numbers = torch.stack([value.double() for value in (*detached, parts.total.detach().reshape(()))]).tolist()
    parts.values = dict(zip(names, numbers[:-1]))
    parts.total_value = numbers[-1]
    return parts


def total_loss(terms: list[LossTerm], context: LossContext) -> tuple[torch.Tensor, dict[str, float]]:
    """Weighted sum of the active terms, and each term's unweighted value (for logging)."""
    parts = loss_parts(terms, context)
    return parts.total, parts.values
