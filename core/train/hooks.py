"""Extension points of the trainer, for the methods built on it (ESGS, the baselines).

A hook is an object with any of the methods of :class:`TrainHook` (subclass it and
override what you need). Every method receives ``run``, a :class:`RunView`: the narrow,
typed part of a training run a hook may read and use (nerfstudio's callbacks see a
similar fixed set of attributes). The trainer calls them in the order the hooks were given:

- ``initial_points(run) -> SeedPoints | None`` once, when a run starts from scratch (not
  when resuming), after the scene is loaded and before the Gaussians exist: more points to
  seed Gaussians from, beside the scene's SfM points (ESGS adds points of its depth prior);
- ``setup(run)`` once, after the scene and the Gaussians exist and before the first
  step (also when resuming, before the checkpoint is loaded): add loss terms
  (``run.add_loss_term``), optimizer groups for an ``nn.Module``'s parameters
  (``run.add_parameter_group``), load prior maps...
- ``before_render(run, context, params) -> params``: change the rendering parameters
  (GPDFN fuses neighbours here; the result must stay differentiable w.r.t. the
  Gaussians) or request channels by setting ``context.render_depth`` /
  ``context.render_normals``;
- ``model_params(run, params) -> params``: the parameters as the method shows its model
  outside a training step (GPDFN fuses neighbours, Mip-Splatting filters); used by
  ``Trainer.render_model`` to render the model as it trains;
- ``view_params(run, view, params) -> params``: the parameters to render one view with
  outside a training step, after ``model_params`` (``Trainer.render_model``) or after
  ``export_model`` (the end-of-run evaluation of the held-out views); a view-dependent model
  (Scaffold-GS decodes its anchors for the view's camera) returns them here;
- ``after_backward(run, context)``: gradients exist, the optimizer has not stepped;
- ``on_densify(run, report)``: the Gaussian set changed (clone/split/prune or an
  opacity reset); ``report.source_index`` [N_new] maps every Gaussian to the one it came
  from, so per-Gaussian state can be remapped with ``state[report.source_index]``;
- ``export_model(run, gaussians) -> gaussians``: at the end of a run, the model that is
  written to point_cloud.ply and evaluated (GPDFN returns a copy with its residuals baked
  in; checkpoints keep the raw Gaussians so training can resume);
- ``state_dict()`` / ``load_state_dict(state)``: saved in and restored from checkpoints
  (tensors, numbers, strings, lists and dicts only).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Optional, Protocol, Sequence

if TYPE_CHECKING:
    import numpy as np
    import torch

    from .dataset import View
    from .densify import DensifyReport
    from .gaussians import GaussianModel, RenderParams
    from .losses import LossTerm


@dataclass
class StepContext:
    """What the trainer knows about the current step; hooks may read and annotate it.

    ``view``: the :class:`~.dataset.View` being trained on; ``sh_degree``: active SH
    degree; ``render_depth``/``render_normals``: channels to render (set by the active
    loss terms, hooks may switch them on); after rendering ``output`` holds the
    :class:`~.rendering.RenderOutput`, after the loss ``loss`` (tensor) and
    ``loss_values`` (per term, unweighted). Once ``after_backward`` has run, ``output`` is
    dropped and ``loss`` detached, so that the step's graph and buffers (and, through the
    graph, parameters that densification replaces) are freed before the optimizer steps.
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


class RunView(Protocol):
    """What a hook sees of a training run: read-only facts and four actions.

    Facts: ``seed`` (the run's seed), ``scene`` (the folder the scene's files, priors
    included, are read from), ``device``, ``backend`` (the rasterizer backend it renders
    with: cpu, reference or cuda), ``train_views`` / ``test_views``
    (:class:`~.dataset.View`), ``extent`` (3DGS's scene extent of the training cameras, the
    scale the learning rates and densification use), ``gaussians`` (the :class:`~.gaussians.GaussianModel` being
    trained; its tensors change at densification, the object does not) and
    ``scaled_step(reference_step)`` (a step of the 30,000-step reference schedule moved to
    this run's length). Actions: ``add_loss_term``, ``add_parameter_group``, ``message``,
    ``render(params, view, ...)`` with the run's backend, background and render options, and
    ``render_model(view)``: the model being trained as its method shows it (no gradients).
    """

    @property
    def seed(self) -> int: ...

    @property
    def scene(self) -> Path: ...

    @property
    def device(self) -> "torch.device": ...

    @property
    def backend(self) -> str: ...

    @property
    def train_views(self) -> Sequence["View"]: ...

    @property
    def test_views(self) -> Sequence["View"]: ...

    @property
    def extent(self) -> float: ...

    @property
    def gaussians(self) -> "GaussianModel": ...

    def scaled_step(self, reference_step: int, *, minimum: int = 0) -> int: ...

    def add_loss_term(self, term: "LossTerm") -> None: ...

    def add_parameter_group(self, name: str, params: "torch.Tensor | Iterable[torch.Tensor]", lr: float, *,
                            schedule: Any = None) -> None: ...

    def message(self, text: str) -> None: ...

    def render(self, params: "RenderParams", view: "View", *, render_depth: bool = False,
               render_normals: bool = False) -> Any: ...

    def render_model(self, view: "View", *, sh_degree: Optional[int] = None, render_depth: bool = False,
                     render_normals: bool = False) -> Any: ...


@dataclass(frozen=True)
class SeedPoints:
    """Points a hook adds to the initial Gaussians: xyz [M, 3] world coordinates (float64) and
    rgb [M, 3] colours in [0, 1], seeded like the SfM points (same opacity; scales from the
    nearest neighbours among all the points)."""

    xyz: "np.ndarray"
    rgb: "np.ndarray"


class TrainHook:
    """Base class with do-nothing implementations of every hook method."""

    #: Key of this hook's state in checkpoints; must be unique among a run's hooks.
    name: str = "hook"

    def initial_points(self, run: RunView) -> Optional[SeedPoints]:
        """Points to seed Gaussians from besides the SfM points (default: none)."""
        return None

    def setup(self, run: RunView) -> None:
        pass

    def before_render(self, run: RunView, context: StepContext, params: "RenderParams") -> Optional["RenderParams"]:
        return params

    def model_params(self, run: RunView, params: "RenderParams") -> "RenderParams":
        """The parameters as this method shows its model between steps (default: unchanged)."""
        return params

    def view_params(self, run: RunView, view: "View", params: "RenderParams") -> "RenderParams":
        """The parameters to render ``view`` with outside a training step (default: unchanged)."""
        return params

    def after_backward(self, run: RunView, context: StepContext) -> None:
        pass

    def on_densify(self, run: RunView, report: "DensifyReport") -> None:
        pass

    def export_model(self, run: RunView, gaussians: "GaussianModel") -> "GaussianModel":
        """The Gaussians to write and evaluate at the end (GPDFN folds its residuals in)."""
        return gaussians

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass
