"""Densification strategies: who adds, removes and reorders Gaussians during training.

The trainer owns the loop; a :class:`Strategy` owns adaptive density control and its
statistics (the idea of gsplat's ``Strategy`` classes). The trainer calls it at three points
of every step:

1. ``step_pre_backward(step, output)``: the render exists, the loss is not yet
   differentiated (a strategy that needs extra gradients asks for them here);
2. ``step_post_backward(step, view, output)``: gradients exist, the optimizer has not
   stepped (gather statistics, e.g. screen-space gradient norms);
3. ``step_post_optimizer(step) -> [DensifyReport]``: the parameters were updated; change
   the Gaussian set here and return one report per change. Each report's
   ``source_index`` [N_after] names, for every Gaussian after the change, the one it came
   from, so hooks remap their per-Gaussian state with ``state[source_index]``.

A strategy changes parameters, their Adam moments and its own statistics together (through
:class:`~.optim.TrainOptimizer`'s ``append``/``select``/``reset``), so the three stay
aligned; its state is saved in checkpoints under ``"densify"``.

:class:`DefaultStrategy` is 3DGS's clone / split / prune / opacity reset, with optional
Morton (Z-order) sorting of the Gaussians after every change (``spatial_order``) and the
pruning of hidden Gaussians when densification ends (``prune_hidden``).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any, Callable, Optional

import torch

from .contribution import Visibility
from .densify import DensifyReport, DensifySettings, DensifyState, densify_and_prune, reset_opacity
from .gaussians import GaussianModel
from .optim import TrainOptimizer
from .spatial_order import sort_gaussians


@dataclass
class StrategyContext:
    """What a strategy works on, handed to :meth:`Strategy.setup` once the run's objects exist.

    ``extent``: the scene's extent (scene units) that size thresholds are fractions of;
    ``generator``: the run's seeded random generator (split children are sampled from it);
    ``message``: sends a line to the run's progress (warnings, summaries).
    """

    gaussians: GaussianModel
    optimizer: TrainOptimizer
    extent: float
    device: torch.device
    generator: torch.Generator
    message: Callable[[str], None]
    #: the Gaussians' :class:`~.contribution.Visibility` over the training views, as the
    #: method renders them; None where the caller cannot render (then nothing is pruned as hidden)
    visibility: Optional[Callable[[], Visibility]] = None


class Strategy:
    """Base class: a strategy that never changes the Gaussian set (override what you need)."""

    #: Name shown in logs and the run's config.
    name: str = "none"

    def prepare_initial(self, gaussians: GaussianModel) -> None:
        """Called once on a fresh run's initial Gaussians, before the optimizer exists."""

    def setup(self, context: StrategyContext) -> None:
        """Called once the optimizer exists (fresh runs and resumed runs)."""
        self.context = context

    def step_pre_backward(self, step: int, output: Any) -> None:
        """The step's render ``output`` exists; the loss is not differentiated yet."""

    def gathers_statistics(self, step: int) -> bool:
        """Whether :meth:`step_post_backward` reads screen-space gradients at ``step`` (the trainer
        then keeps the densifying terms' share apart, ``output.meta['densify_grad']``)."""
        return False

    def step_post_backward(self, step: int, view: Any, output: Any) -> None:
        """Gradients of this step exist (``output.meta['means2d'].grad``, and
        ``output.meta['densify_grad']`` when the trainer split the loss); the optimizer has not stepped."""

    def step_post_optimizer(self, step: int) -> list[DensifyReport]:
        """Change the Gaussian set after the optimizer step; one report per change."""
        return []

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


@dataclass(frozen=True)
class DefaultStrategySettings:
    """The thresholds and switches of 3DGS's density control (from :class:`~.config.TrainConfig`)."""

    grad_threshold: float
    percent_dense: float
    prune_opacity: float
    max_screen_size_px: float
    max_world_size: float
    max_gaussians: int
    opacity_reset_value: float
    spatial_order: bool
    #: at the end of densification, prune the Gaussians that less than this share of light
    #: reaches in every training view (0 = never; see :mod:`.contribution`)
    prune_hidden: float = 0.0


class DefaultStrategy(Strategy):
    """3DGS's adaptive density control on a scaled :class:`~.config.Schedule`.

    Statistics: the NDC screen-space gradient norm of every visible Gaussian, accumulated
    while the schedule densifies. Changes: clone/split/prune on densification steps, then
    (with ``spatial_order``) one permutation back into Morton order of the centres, folded
    into the report's ``source_index``; opacity clamping on reset steps (a report with
    ``reset_opacity=True`` and the identity index); with ``prune_hidden`` > 0, at the first step
    after densification, removal of the Gaussians hidden in every training view (the
    context's ``visibility``; :mod:`.contribution`).
    """

    name = "default"

    def __init__(self, settings: DefaultStrategySettings, schedule: Any):
        self.settings = settings
        self.schedule = schedule
        self.state: Optional[DensifyState] = None

    @classmethod
    def from_config(cls, config: Any) -> "DefaultStrategy":
        """The default strategy of a :class:`~.config.TrainConfig` (its densify_* and prune_* settings)."""
        settings = DefaultStrategySettings(
            grad_threshold=config.densify_grad_threshold, percent_dense=config.percent_dense,
            prune_opacity=config.prune_opacity, max_screen_size_px=config.prune_screen_size_px,
            max_world_size=config.prune_world_size, max_gaussians=config.max_gaussians,
            opacity_reset_value=config.opacity_reset_value, spatial_order=config.spatial_order,
            prune_hidden=config.prune_hidden)
        return cls(settings, config.schedule())

    def prepare_initial(self, gaussians: GaussianModel) -> None:
        if self.settings.spatial_order:
            sort_gaussians(gaussians)  # before the optimizer and the hooks exist: nothing else to move

    def setup(self, context: StrategyContext) -> None:
        super().setup(context)
        self.state = DensifyState.zeros(len(context.gaussians), context.device)

    def gathers_statistics(self, step: int) -> bool:
        return bool(self.schedule.accumulates_gradients(step))

    def step_post_backward(self, step: int, view: Any, output: Any) -> None:
        means2d = output.meta.get("means2d")
        if not (self.schedule.accumulates_gradients(step) and means2d is not None
                and means2d.shape[1] == len(self.context.gaussians)):
            return
        # the densifying terms' share when the trainer split the loss (prior losses left out)
        gradient = output.meta.get("densify_grad", means2d.grad)
        if gradient is not None:
            with torch.no_grad():
                self.state.accumulate(gradient, output.meta["radii"], view.width, view.height)

    def step_post_optimizer(self, step: int) -> list[DensifyReport]:
        reports = []
        if self.schedule.is_densify_step(step):
            reports.append(self._densify(step))
        if self.schedule.is_opacity_reset_step(step):
            gaussians = self.context.gaussians
            reset_opacity(gaussians, self.context.optimizer, self.settings.opacity_reset_value)
            reports.append(DensifyReport(step=step, count_before=len(gaussians), count_after=len(gaussians),
                                         reset_opacity=True,
                                         source_index=torch.arange(len(gaussians), device=self.context.device)))
        if self.prunes_hidden(step):
            reports.append(self._prune_hidden(step))
        return reports

    def prunes_hidden(self, step: int) -> bool:
        """Whether ``step`` prunes hidden Gaussians: the first step without densification, when
        the set is final but the remaining steps can still mend what the pruning changed."""
        schedule = self.schedule
        return (self.settings.prune_hidden > 0 and self.context.visibility is not None
                and 0 < schedule.densify_until == step < schedule.iterations)

    def _prune_hidden(self, step: int) -> DensifyReport:
        context, threshold = self.context, self.settings.prune_hidden
        gaussians = context.gaussians
        count = len(gaussians)
        visibility = context.visibility()
        hidden = visibility.hidden(threshold).to(context.device)
        everything_seen = int(hidden.sum()) == int(visibility.seen.sum())
        if not hidden.any() or everything_seen:
            if hidden.any():
                context.message(f"warning: every Gaussian in view is hidden (less than {threshold:g} of the light in "
                                "every training view); none pruned")
            return DensifyReport(step=step, count_before=count, count_after=count,
                                 source_index=torch.arange(count, device=context.device))
        keep = ~hidden
        kept = int(keep.sum())
        with torch.no_grad():
            gaussians.set_params(context.optimizer.select(keep))
        self.state.select(keep)
        context.message(f"pruned {count - kept} of {count} Gaussians hidden in every training view (less than "
                        f"{threshold:g} of the light reaches them)")
        return DensifyReport(step=step, count_before=count, count_after=kept, pruned=count - kept,
                             source_index=keep.nonzero().squeeze(1))

    def _densify(self, step: int) -> DensifyReport:
        settings, context = self.settings, self.context
        thresholds = DensifySettings(
            grad_threshold=settings.grad_threshold, percent_dense=settings.percent_dense, extent=context.extent,
            prune_opacity=settings.prune_opacity, prune_large=self.schedule.prunes_large(step),
            max_screen_size_px=settings.max_screen_size_px, max_world_size=settings.max_world_size,
            max_gaussians=settings.max_gaussians)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            report = densify_and_prune(context.gaussians, context.optimizer, self.state, thresholds, step=step,
                                       generator=context.generator)
        if settings.spatial_order:
            # clones and split children were appended at the end: one permutation of every
            # per-Gaussian tensor (parameters, Adam moments, statistics) restores the spatial
            # order, and the hooks see it folded into the report's source_index
            order = sort_gaussians(context.gaussians, context.optimizer, self.state)
            if order is not None and report.source_index is not None:
                report.source_index = report.source_index[order]
        for warning in caught:
            context.message(f"warning: {warning.message}")
            warnings.warn(warning.message, RuntimeWarning, stacklevel=3)
        return report

    def state_dict(self) -> dict:
        return self.state.state_dict() if self.state is not None else {}

    def load_state_dict(self, state: dict) -> None:
        if state and self.state is not None:
            self.state.load_state_dict(state)
