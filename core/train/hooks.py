"""Extension points of the trainer, for the ESGS modules (priors, GPDFN, NDN).

A hook is an object with any of the methods of :class:`TrainHook` (subclass it and
override what you need). The trainer calls them in the order the hooks were given:

- ``setup(trainer)`` once, after the scene and the Gaussians exist and before the first
  step (also when resuming, before the checkpoint is loaded): add loss terms
  (``trainer.add_loss_term``), optimizer groups for an ``nn.Module``'s parameters
  (``trainer.add_parameter_group``), load prior maps...
- ``before_render(trainer, context, params) -> params``: change the rendering parameters
  (GPDFN fuses neighbours here; the result must stay differentiable w.r.t. the
  Gaussians) or request channels by setting ``context.render_depth`` /
  ``context.render_normals``;
- ``after_backward(trainer, context)``: gradients exist, the optimizer has not stepped;
- ``on_densify(trainer, report)``: the Gaussian set changed (clone/split/prune or an
  opacity reset); ``report.source_index`` [N_new] maps every Gaussian to the one it came
  from, so per-Gaussian state can be remapped with ``state[report.source_index]``;
- ``export_model(trainer, gaussians) -> gaussians``: at the end of a run, the model that is
  written to point_cloud.ply and evaluated (GPDFN returns a copy with its residuals baked
  in; checkpoints keep the raw Gaussians so training can resume);
- ``state_dict()`` / ``load_state_dict(state)``: saved in and restored from checkpoints
  (tensors, numbers, strings, lists and dicts only).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Optional

if TYPE_CHECKING:
    from .densify import DensifyReport
    from .gaussians import RenderParams


@dataclass
class StepContext:
    """What the trainer knows about the current step; hooks may read and annotate it.

    ``view``: the :class:`~.dataset.View` being trained on; ``sh_degree``: active SH
    degree; ``render_depth``/``render_normals``: channels to render (set by the active
    loss terms, hooks may switch them on); after rendering ``output`` holds the
    :class:`~.rendering.RenderOutput`, after the loss ``loss`` (tensor) and
    ``loss_values`` (per term, unweighted).
    """

    step: int
    view: Any
    sh_degree: int
    render_depth: bool = False
    render_normals: bool = False
    output: Any = None
    loss: Any = None
    loss_values: dict[str, float] = field(default_factory=dict)
    extras: dict[str, Any] = field(default_factory=dict)


class TrainHook:
    """Base class with do-nothing implementations of every hook method."""

    #: Key of this hook's state in checkpoints; must be unique among a run's hooks.
    name: str = "hook"

    def setup(self, trainer: Any) -> None:
        pass

    def before_render(self, trainer: Any, context: StepContext, params: "RenderParams") -> Optional["RenderParams"]:
        return params

    def after_backward(self, trainer: Any, context: StepContext) -> None:
        pass

    def on_densify(self, trainer: Any, report: "DensifyReport") -> None:
        pass

    def export_model(self, trainer: Any, gaussians: Any) -> Any:
        """The Gaussians to write and evaluate at the end (GPDFN folds its residuals in)."""
        return gaussians

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass
