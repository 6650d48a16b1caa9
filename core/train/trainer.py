"""The training loop: 3DGS on a COLMAP scene, extended by a method's hooks and strategy.

Public entry point: :func:`train` (a run of the plain 3DGS method, or of any
:class:`~.method.Method` passed in; :func:`esgs.core.methods.train` looks the method up by
``config.method``). The trainer imports nothing above the training layer. One step:

1. pick a training view (a shuffled pass over the views, as 3DGS), update learning rates;
2. build the rendering parameters, let hooks modify them (``before_render``);
3. render colour (plus depth/normals when an active loss term or a hook asks);
4. total loss = weighted active terms (L1 + D-SSIM for the baseline); stop on NaN/Inf;
5. backward, ``after_backward`` hooks, densification statistics, Adam step;
6. the densification strategy (:class:`~.strategy.DefaultStrategy`: densify / prune / reset
   opacity on schedule, Morton order kept) changes the Gaussian set, then ``on_densify`` hooks;
7. parameters checked finite; checkpoint, progress event, stop requests.

Stops: SIGTERM (and Ctrl-C) finish the current step, save a checkpoint and return with
status "interrupted"; ``max_minutes`` saves, writes the PLY and evaluates (status
"time_limit"). A NaN/Inf raises :class:`TrainingDivergedError` and leaves the last good
checkpoint as the newest one.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterable, Optional, Sequence

import numpy as np
import torch

from ..config import config_to_dict, save_config
from ..errors import CheckpointError, ConfigError, ESGSError
from ..io_utils import atomic_write_json
from ..progress import JsonLinesProgress, ProgressCallback, ProgressEvent, combine
from ..runtime.stop import StopRequests
from .checkpoint import latest_checkpoint, list_checkpoints, load_checkpoint, save_checkpoint
from .config import TrainConfig, run_config_from_dict
from .dataset import SceneData, check_scene_folder, load_scene_data
from .dataset import View
from .gaussians import GaussianModel, RenderParams
from .hooks import StepContext, TrainHook
from .memory import release_free_memory
from .losses import LossContext, LossParts, LossTerm, loss_parts, needed_channels, photometric_terms
from .method import PLAIN_3DGS, Method, MethodParts
from .optim import ExponentialDecay, TrainOptimizer
from .rendering import RenderOutput, backend_device, render_view, resolve_backend
from ..formats.run_dir import RunDir
from ..formats.scene_dir import PriorSource
from .sky import SkyModel, UnseenSkyPrior, save_sky
from .contribution import Visibility, training_visibility
from .strategy import DefaultStrategy, Strategy, StrategyContext
from .tensorboard import TensorBoardScalars, summary_writer_class

#: Settings that may change when a run is resumed (they do not change what is computed).
RESUMABLE_SETTINGS = frozenset({
    "scene", "out", "resume", "max_minutes", "threads", "events", "stop_file", "checkpoint_every", "keep_checkpoints",
    "progress_every", "evaluate", "save_renders", "lpips", "backend", "tensorboard", "eval_every",
})

CHECKPOINT_FORMAT = 1


class TrainingDivergedError(ESGSError):
    """The loss or a parameter became NaN/Inf; the last good checkpoint is kept."""


@dataclass
class TrainResult:
    """What :func:`train` did.

    status: "completed", "time_limit" (max_minutes reached; evaluated) or "interrupted"
    (SIGTERM/Ctrl-C; checkpoint saved, resume with ``resume=True``). ``elapsed_s``: seconds
    of the run up to its end (every session, the end-of-run evaluation and writes included;
    mid-run evaluations, ``eval_every``, excluded); ``train_s``: the training seconds when the
    last step ended (the same clock without the end-of-run work; the time of the last point
    of the evaluation curve).
    """

    run_dir: Path
    status: str
    step: int
    iterations: int
    n_gaussians: int
    elapsed_s: float
    metrics: Optional[dict] = None
    point_cloud: Optional[Path] = None
    checkpoint: Optional[Path] = None
    train_s: Optional[float] = None

    def to_dict(self) -> dict:
        return {"run_dir": str(self.run_dir), "status": self.status, "step": self.step,
                "iterations": self.iterations, "n_gaussians": self.n_gaussians, "elapsed_s": self.elapsed_s,
                "train_s": self.train_s,
                "point_cloud": str(self.point_cloud) if self.point_cloud else None,
                "checkpoint": str(self.checkpoint) if self.checkpoint else None}


class ViewSampler:
    """3DGS's view order: every view once per pass, in a fresh random order each pass."""

    def __init__(self, count: int, seed: int):
        self.count = count
        self.rng = np.random.default_rng(seed)
        self.order: list[int] = []

    def next(self) -> int:
        if not self.order:
            self.order = [int(i) for i in self.rng.permutation(self.count)]
        return self.order.pop()

    def state_dict(self) -> dict:
        return {"rng": self.rng.bit_generator.state, "order": list(self.order)}

    def load_state_dict(self, state: dict) -> None:
        self.rng.bit_generator.state = state["rng"]
        self.order = [int(i) for i in state["order"]]


class Trainer:
    """A training run. Use :func:`train`.

    ``method`` (default: plain 3DGS) must be the :class:`~.method.Method` named by
    ``config.method``; its parts (hooks, strategy, render options) are built here from
    ``config.method_config``. Hooks see the run through :class:`~.hooks.RunView`, which the
    trainer implements: ``seed``, ``scene``, ``device``, ``train_views``, ``test_views``,
    ``gaussians``, ``scaled_step``, ``add_loss_term``, ``add_parameter_group``, ``message``
    and ``render``. :meth:`render_model` renders the model as the method shows it (every
    hook's ``model_params``, then its ``view_params`` for the view; the end-of-run evaluation
    passes the exported model's parameters through ``view_params`` too).
    """

    def __init__(self, config: TrainConfig, progress: Optional[ProgressCallback] = None,
                 hooks: Sequence[TrainHook] = (), *, method: Method = PLAIN_3DGS):
        if config.method != method.name:
            raise ConfigError(f"this run's method is {config.method!r} but the trainer was given {method.name!r}",
                              hint="train through esgs.core.methods.train(config), which looks the method up")
        # a copy: the caller's config (a dict of settings, perhaps) is left as it was given
        config = replace(config, method_config=method.settings_of(config))
        config.validate()
        if config.scene is None or config.out is None:
            raise ConfigError("both scene and out must be set", hint="esgs train SCENE --out RUN_DIR")
        self.method = method
        self.parts: MethodParts = method.build(config.method_config, config)
        hooks = [*self.parts.hooks, *hooks]
        names = [getattr(hook, "name", type(hook).__name__) for hook in hooks]
        if len(set(names)) != len(names):
            raise ConfigError(f"hook names must be unique, got {names}")
        self.config = config
        self.hooks = list(hooks)
        self.strategy: Strategy = self.parts.strategy or DefaultStrategy.from_config(config)
        self.user_progress = progress
        self.run_dir = RunDir(Path(config.out))
        self.schedule = config.schedule()
        self.backend = resolve_backend(config.backend)
        self.device = backend_device(self.backend)
        self.loss_terms: list[LossTerm] = photometric_terms(config.lambda_dssim)
        self.background = torch.tensor(config.background, dtype=torch.float32, device=self.device)
        self.sky: Optional[SkyModel] = None
        self._unseen_sky: Optional[UnseenSkyPrior] = None
        self.num_threads = config.threads or None
        self.step = 0
        self.loss_ema: Optional[float] = None
        self.psnr_ema: Optional[float] = None
        self.elapsed_before_s = 0.0
        #: seconds of this session spent outside training (mid-run evaluations), off its clock
        self._paused_s = 0.0
        self.data: SceneData
        self.gaussians: GaussianModel
        self.optimizer: TrainOptimizer
        self._progress: ProgressCallback = progress or (lambda event: None)
        self._events_files: list[JsonLinesProgress] = []
        self._scalars: Optional[TensorBoardScalars] = None
        if config.tensorboard is not None:
            summary_writer_class()  # a missing optional package fails here, before any training work

    # --- the RunView that hooks see (see hooks.RunView) -----------------------------
    @property
    def seed(self) -> int:
        return self.config.seed

    @property
    def scene(self) -> Path:
        """The folder the scene's files (priors included) are read from."""
        return Path(self.data.source or self.config.scene)

    @property
    def extent(self) -> float:
        return self.data.extent

    @property
    def train_views(self) -> Sequence[View]:
        return self.data.train

    @property
    def test_views(self) -> Sequence[View]:
        return self.data.test

    def scaled_step(self, reference_step: int, *, minimum: int = 0) -> int:
        """A step of the 30,000-step reference schedule, moved to this run's length."""
        return self.config.scaled_step(reference_step, minimum=minimum)

    def add_loss_term(self, term: LossTerm) -> None:
        """Add a named term to the total loss (names must be unique)."""
        if any(existing.name == term.name for existing in self.loss_terms):
            raise ConfigError(f"a loss term named {term.name!r} exists already")
        self.loss_terms.append(term)

    def add_parameter_group(self, name: str, params: torch.Tensor | Iterable[torch.Tensor], lr: float, *,
                            schedule: Any = None) -> None:
        """Optimise a module's parameters with Adam alongside the Gaussians (not densified)."""
        self.optimizer.add_group(name, params, lr, schedule=schedule, per_gaussian=False)

    def render(self, params: RenderParams, view: Any, *, render_depth: bool = False,
               render_normals: bool = False):
        """Render ``params`` into a :class:`~.dataset.View` with this run's backend and background."""
        return render_view(params, view.viewmat.to(self.device), view.K.to(self.device), view.width, view.height,
                           background=self.background, render_depth=render_depth, render_normals=render_normals,
                           backend=self.backend, num_threads=self.num_threads,
                           antialiased=self.parts.render.antialiased, eps2d=self.parts.render.eps2d, sky=self.sky)

    def render_model(self, view: View, *, sh_degree: Optional[int] = None, render_depth: bool = False,
                     render_normals: bool = False) -> RenderOutput:
        """Render the model being trained as its method shows it (every hook's ``model_params``
        applied: GPDFN's fusion, Mip-Splatting's filter), without gradients.

        ``sh_degree`` defaults to the degree active at the current step.
        """
        degree = self.schedule.sh_degree_at(self.step, self.config.sh_degree) if sh_degree is None else sh_degree
        with torch.no_grad():
            params = self.gaussians.render_params(degree)
            for hook in self.hooks:
                params = hook.model_params(self, params)
            params = self._view_params(view, params)
            return self.render(params, view, render_depth=render_depth, render_normals=render_normals)

    def training_visibility(self) -> Visibility:
        """The Gaussians' :class:`~.contribution.Visibility` over the training views, as the
        method renders them (hooks' ``model_params`` applied; per-view randomness such as
        dropout left out), on this run's backend."""
        with torch.no_grad():
            params = self.gaussians.render_params(0)
            for hook in self.hooks:
                params = hook.model_params(self, params)
        options = self.parts.render

        def render(features: RenderParams, view: View) -> torch.Tensor:
            return render_view(features, view.viewmat.to(self.device), view.K.to(self.device), view.width,
                               view.height, backend=self.backend, num_threads=self.num_threads,
                               antialiased=options.antialiased, eps2d=options.eps2d).image

        def camera(view: View):
            return view.viewmat.to(self.device), view.K.to(self.device), view.width, view.height

        return training_visibility(params, self.data.train, render, camera, antialiased=options.antialiased,
                                   eps2d=options.eps2d)

    def _view_params(self, view: View, params: RenderParams) -> RenderParams:
        """``params`` passed through every hook's ``view_params`` for ``view``."""
        for hook in self.hooks:
            params = hook.view_params(self, view, params)
        return params

    def message(self, text: str) -> None:
        """Send a message event (warnings, densification summaries) to the progress callbacks."""
        self._progress(ProgressEvent(step=self.step, total=self.config.iterations, stage="train",
                                     kind="message", message=text))

    # --- setup ---------------------------------------------------------------------
    def _setup_runtime(self) -> None:
        if self.config.threads:
            torch.set_num_threads(self.config.threads)
        torch.manual_seed(self.config.seed)
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(self.config.seed)
        self.sampler_seed = self.config.seed

    def _initial_gaussians(self) -> GaussianModel:
        config = self.config
        kwargs = dict(max_sh_degree=config.sh_degree, init_opacity=config.init_opacity,
                      neighbours=config.init_scale_neighbours)
        points_xyz, points_rgb = self.data.points_xyz, self.data.points_rgb
        for hook in self.hooks:
            seeds = hook.initial_points(self)
            if seeds is not None and len(seeds.xyz):
                points_xyz = np.concatenate([points_xyz, np.asarray(seeds.xyz, dtype=np.float64)])
                points_rgb = np.concatenate([points_rgb, np.asarray(seeds.rgb, dtype=points_rgb.dtype)])
        if len(points_xyz):
            if not len(self.data.points_xyz):
                self.message(f"the COLMAP model has no 3D points: starting from the {len(points_xyz):,} seeded points")
            model = GaussianModel.from_points(points_xyz, points_rgb, **kwargs)
        else:
            self.message(f"the COLMAP model has no 3D points: starting from {config.random_init_points} random Gaussians")
            rng = np.random.default_rng(config.seed)
            model = GaussianModel.random(config.random_init_points, self.data.center, self.data.extent, rng, **kwargs)
        self.strategy.prepare_initial(model)
        return model

    def _build_optimizer(self) -> None:
        config, extent = self.config, self.data.extent
        optimizer = TrainOptimizer()
        params = self.gaussians.params
        position = ExponentialDecay(config.position_lr_init * extent, config.position_lr_final * extent,
                                    max_steps=config.iterations, delay_steps=self.schedule.position_lr_delay_steps,
                                    delay_mult=config.position_lr_delay_mult)
        optimizer.add_group("means", params["means"], position(0), schedule=position, per_gaussian=True)
        optimizer.add_group("sh_dc", params["sh_dc"], config.feature_lr, per_gaussian=True)
        optimizer.add_group("sh_rest", params["sh_rest"], config.feature_lr / 20.0, per_gaussian=True)
        optimizer.add_group("opacity_logit", params["opacity_logit"], config.opacity_lr, per_gaussian=True)
        optimizer.add_group("log_scales", params["log_scales"], config.scaling_lr, per_gaussian=True)
        optimizer.add_group("quats", params["quats"], config.rotation_lr, per_gaussian=True)
        self.optimizer = optimizer

    def setup(self, checkpoint: Optional[dict] = None) -> None:
        """Load the scene, build Gaussians, optimizer and hooks (from ``checkpoint`` when given)."""
        self._setup_runtime()
        config = self.config
        self.data = load_scene_data(config.scene, images_dir=config.images_dir, resolution=config.resolution,
                                    width=config.width, test_every=config.test_every, mask_source=config.mask_source)
        if checkpoint is not None:
            self.gaussians = GaussianModel.from_state_dict(checkpoint["gaussians"])
        else:
            self.gaussians = self._initial_gaussians()
        self.gaussians.to(self.device)
        self.grayscale = config.grayscale == "on" or (
            config.grayscale == "auto" and all(_is_grey(view.image) for view in self.data.train))
        if self.grayscale:
            self.message("every training image is grey: the Gaussians' colours are kept grey (--grayscale off to "
                         "learn colours)" if config.grayscale == "auto" else "colours are kept grey (--grayscale on)")
        self._build_optimizer()
        self._setup_sky()
        if self.grayscale:
            self._make_grey()
        self.strategy.setup(StrategyContext(gaussians=self.gaussians, optimizer=self.optimizer, extent=self.data.extent,
                                            device=self.device, generator=self.generator, message=self.message,
                                            visibility=self.training_visibility))
        self.sampler = ViewSampler(len(self.data.train), config.seed)
        for hook in self.hooks:
            hook.setup(self)
        if checkpoint is not None:
            self._load_state(checkpoint)
        # loading left ~100 MiB of freed heap (decoded files, the COLMAP model's objects)
        release_free_memory()

    def _make_grey(self) -> None:
        """Project the colour parameters (SH of the Gaussians and of the sky) onto grey:
        each coefficient's R, G and B become their mean."""
        with torch.no_grad():
            tensors = [self.gaussians.params["sh_dc"], self.gaussians.params["sh_rest"]]
            if self.sky is not None:
                tensors += list(self.sky.parameters())
            for tensor in tensors:
                if tensor.numel() and tensor.shape[-1] == 3:
                    tensor.copy_(tensor.mean(dim=-1, keepdim=True).expand_as(tensor))

    def _setup_sky(self) -> None:
        """The sky model and its loss on the mask source's sky pixels (see :mod:`.sky`)."""
        config = self.config
        if config.sky != "envmap":
            return
        self.sky = SkyModel(config.sky_degree, grid_rows=config.sky_grid_rows).to(self.device)  # no random draw: same seed, same run
        marks_sky = _marks_sky(self.data.mask_source)
        # start from the mean colour of the pixels the masks call sky; without any, from the mean
        # colour of the images (sky_init images: held-out ground beyond every training view's
        # reach then shows the ground's mean colour rather than black) or black (3DGS's background)
        colour = _mean_colour(self.data.train, sky=True) if marks_sky else None
        if colour is None and config.sky_init == "images":
            colour = _mean_colour(self.data.train, sky=False)
        if colour is not None:
            self.sky.set_color(colour)
        decay = ExponentialDecay(config.sky_lr, config.sky_lr * config.sky_lr_decay, max_steps=config.iterations)
        self.optimizer.add_group("sky", list(self.sky.parameters()), config.sky_lr, schedule=decay, per_gaussian=False)
        if config.sky_alpha_weight > 0 and marks_sky:
            self.add_loss_term(LossTerm("sky_alpha", config.sky_alpha_weight, _sky_alpha_term))
        if config.sky_smooth_weight > 0:
            # a prior on the sky model itself: no masks needed, the same on every step
            self.add_loss_term(LossTerm("sky_smooth", config.sky_smooth_weight, self._sky_smooth_term))
        if config.surface_alpha_weight > 0 and marks_sky:
            self.add_loss_term(LossTerm("surface_alpha", config.surface_alpha_weight, _surface_alpha_term))
        if config.sky_unseen_weight > 0:
            self._unseen_sky = UnseenSkyPrior.from_views(self.data.train, marks_sky)
            if self._unseen_sky is None:
                self.message("note: every direction was seen by a training view, or none as sky: "
                             "the unseen-sky prior is off")
            else:
                self._unseen_sky = self._unseen_sky.to(self.device)
                self.message(f"unseen-sky prior: {100 * self._unseen_sky.unseen_fraction:.0f} % of the sphere "
                             "no training view saw follows its nearest sky")
                self.add_loss_term(LossTerm("sky_unseen", config.sky_unseen_weight, self._sky_unseen_term))

    def _sky_unseen_term(self, context: LossContext) -> torch.Tensor:
        """The sky model's prior on directions no training view saw (:class:`.sky.UnseenSkyPrior`)."""
        return self._unseen_sky.loss(self.sky)

    def _sky_smooth_term(self, context: LossContext) -> torch.Tensor:
        """The sky model's Dirichlet energy (:meth:`.sky.SkyModel.dirichlet_energy`): the
        smoothness prior that keeps directions no view saw near the mean colour."""
        return self.sky.dirichlet_energy()

    # --- checkpoints ---------------------------------------------------------------
    def _state(self) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "step": self.step,
            "config": config_to_dict(self.config),
            # shared, not cloned: torch.save writes it before the next step changes anything
            "gaussians": self.gaussians.state_dict(copy=False),
            "optimizer": self.optimizer.state_dict(),
            "densify": self.strategy.state_dict(),
            "sampler": self.sampler.state_dict(),
            "torch_rng": torch.get_rng_state(),
            "generator": self.generator.get_state().cpu(),
            "hooks": {getattr(h, "name", type(h).__name__): h.state_dict() for h in self.hooks},
            "sky": self.sky.to_dict() if self.sky is not None else None,
            "loss_ema": self.loss_ema,
            "psnr_ema": self.psnr_ema,
            "elapsed_s": self.elapsed_before_s + self._session_elapsed(),
        }

    def _load_state(self, state: dict) -> None:
        if state.get("format") != CHECKPOINT_FORMAT:
            raise CheckpointError(f"checkpoint format {state.get('format')} is not supported (expected {CHECKPOINT_FORMAT})")
        self.step = int(state["step"])
        if self.sky is not None and state.get("sky") is not None:
            self.sky.load_state_dict(SkyModel.from_dict(state["sky"]).to(self.device).state_dict())
        self.optimizer.load_state_dict(state["optimizer"])
        self.strategy.load_state_dict(state["densify"])
        self.sampler.load_state_dict(state["sampler"])
        torch.set_rng_state(state["torch_rng"])
        self.generator.set_state(state["generator"])
        for hook in self.hooks:
            name = getattr(hook, "name", type(hook).__name__)
            if name in state["hooks"]:
                hook.load_state_dict(state["hooks"][name])
        self.loss_ema = state.get("loss_ema")
        self.psnr_ema = state.get("psnr_ema")
        self.elapsed_before_s = float(state.get("elapsed_s", 0.0))

    def save_checkpoint(self) -> Path:
        path = save_checkpoint(self.run_dir.checkpoints, self.step, self._state(), keep=self.config.keep_checkpoints)
        self._last_checkpoint = path
        return path

    def _session_elapsed(self) -> float:
        """Training seconds of this session: its wall time less the mid-run evaluations'."""
        start = getattr(self, "_session_start", None)
        return 0.0 if start is None else time.monotonic() - start - self._paused_s

    def _exported_model(self) -> GaussianModel:
        """The model as the method shows it (every hook's ``export_model``; the trained one untouched)."""
        model = self.gaussians
        for hook in self.hooks:
            model = hook.export_model(self, model) or model
        return model

    def _evaluate_held_out(self, model: GaussianModel, **options: Any) -> dict:
        """:func:`~.evaluate.evaluate_model` of ``model`` on the held-out views as the run renders them."""
        from .evaluate import evaluate_model

        return evaluate_model(model, self.data, backend=self.backend, background=self.background,
                              sh_degree=self.schedule.sh_degree_at(self.step, self.config.sh_degree),
                              num_threads=self.num_threads, antialiased=self.parts.render.antialiased,
                              eps2d=self.parts.render.eps2d, sky=self.sky, view_params=self._view_params, **options)

    def _eval_event(self, step: int, metrics: dict, train_s: float) -> None:
        """One point of the evaluation curve: an "eval" event (events.jsonl) and the TensorBoard scalars."""
        point = {"psnr": metrics["psnr"], "ssim": metrics["ssim"], "train_s": train_s,
                 "n_gaussians": len(self.gaussians)}
        self._progress(ProgressEvent(step=step, total=self.config.iterations, stage="eval", kind="eval",
                                     metrics=point))
        if self._scalars is not None:
            self._scalars.evaluation(step, metrics)

    def _evaluate_during_training(self, step: int) -> None:
        """``eval_every``: PSNR and SSIM of the held-out views now, off the training clock.

        Nothing of the training changes: no gradients, no draw from the run's random
        generators (the rasterizer and the hooks' ``export_model``/``view_params`` draw none),
        the trained parameters untouched (``export_model`` returns a copy where it changes them)."""
        paused = time.monotonic()
        train_s = self.elapsed_before_s + self._session_elapsed()
        try:
            with torch.no_grad():
                metrics = self._evaluate_held_out(self._exported_model(), use_lpips=False)
            if metrics.get("psnr") is not None:
                self._eval_event(step, metrics, train_s)
        finally:
            self._paused_s += time.monotonic() - paused

    # --- one step ------------------------------------------------------------------
    def train_step(self, step: int) -> StepContext:
        """Run training step ``step`` (1-based) and return its context.

        The returned context keeps the loss as a detached tensor and no render output: the
        step's graph and buffers are gone before the optimizer step and densification.
        """
        context, psnr, loss_value = self._gradients(step)
        self.optimizer.step()
        self.optimizer.zero_grad()
        if self.grayscale:
            self._make_grey()

        for report in self.strategy.step_post_optimizer(step):
            for hook in self.hooks:
                hook.on_densify(self, report)
        # a non-finite parameter shows up in the next loss when the Gaussian is in view; the full
        # scan (costly at 100k+ Gaussians) runs periodically and before every checkpoint
        if (step % 50 == 0 or step == self.config.iterations or self._checkpoint_due(step)) \
                and not self.gaussians.all_finite():
            bad = [name for name, p in self.gaussians.params.items() if not bool(torch.isfinite(p).all())]
            self._diverged(f"Gaussian parameters {', '.join(bad)} are not finite after step {step}")

        self.loss_ema = loss_value if self.loss_ema is None else 0.4 * loss_value + 0.6 * self.loss_ema
        self.psnr_ema = psnr if self.psnr_ema is None else 0.4 * psnr + 0.6 * self.psnr_ema
        context.extras["psnr"] = psnr
        return context

    def _gradients(self, step: int) -> tuple[StepContext, float, float]:
        """Render, compute the loss and its gradients for step ``step`` -> (context, PSNR, loss).

        A method of its own so that everything the step built (the render, the loss graph,
        whose leaf accumulators hold the parameters) is released when it returns: kept until
        the end of the step, it lived through densification, which replaces every parameter,
        and through the next step's render (~200 MiB of peak at 400k Gaussians).
        """
        self.step = step
        config = self.config
        view = self.data.train[self.sampler.next()]
        self.optimizer.update_learning_rates(step)
        needs = needed_channels(self.loss_terms, step)
        context = StepContext(step=step, view=view, sh_degree=self.schedule.sh_degree_at(step, config.sh_degree),
                              render_depth="depth" in needs, render_normals="normals" in needs)
        params = self.gaussians.render_params(context.sh_degree)
        for hook in self.hooks:
            replaced = hook.before_render(self, context, params)
            params = replaced if replaced is not None else params
        output = self.render(params, view, render_depth=context.render_depth, render_normals=context.render_normals)
        context.output = output
        self.strategy.step_pre_backward(step, output)
        target = view.image_float(self.device)
        mask = view.mask.to(self.device) if view.mask is not None else None
        image = output.image
        if config.mask_photometric and mask is not None:
            # runs saved before the sky model: masked pixels took the target's colour (no loss there)
            image = torch.where(mask, image, target)
        loss_context = LossContext(step=step, image=image, target=target, mask=mask, alpha=output.alpha,
                                   depth=output.depth, normals=output.normals, view=view, output=output,
                                   params=params, run=self)
        parts = loss_parts(self.loss_terms, loss_context)
        loss, values = parts.total, parts.values
        context.loss, context.loss_values = loss, values
        if not math.isfinite(parts.total_value):
            terms = ", ".join(f"{name}={value:.4g}" for name, value in values.items())
            self._diverged(f"the loss is {parts.total_value} at step {step} ({terms})")
        self._backward(step, parts, output)
        for hook in self.hooks:
            hook.after_backward(self, context)

        self.strategy.step_post_backward(step, view, output)
        with torch.no_grad():
            image = image.detach().clamp(0.0, 1.0)
            mse = float((image - target).pow(2).mean())
        psnr = -10.0 * math.log10(max(mse, 1e-12))
        context.loss, context.output = loss.detach(), None
        return context, psnr, parts.total_value

    def _backward(self, step: int, parts: LossParts, output: Any) -> None:
        """Differentiate the step's loss; with ``densify_gradient = "photometric"`` and terms that
        do not densify (prior losses), on the steps the strategy gathers statistics, in two
        passes: the densifying terms first, their screen-space gradient kept for the strategy as
        ``output.meta["densify_grad"]``, then the others (the parameters' gradients are the sum
        of both passes, the same as one pass)."""
        means2d = output.meta.get("means2d") if isinstance(output.meta, dict) else None
        split = (self.config.densify_gradient == "photometric" and parts.densifying is not None
                 and parts.other is not None and means2d is not None and means2d.requires_grad
                 and self.strategy.gathers_statistics(step))
        if not split:
            parts.total.backward()
            return
        parts.densifying.backward(retain_graph=True)
        output.meta["densify_grad"] = (means2d.grad.detach().clone() if means2d.grad is not None
                                       else torch.zeros_like(means2d))
        parts.other.backward()

    def _checkpoint_due(self, step: int) -> bool:
        every = self.config.checkpoint_every
        return bool(every) and step % every == 0

    def _diverged(self, what: str) -> None:
        last = latest_checkpoint(self.run_dir.checkpoints)
        where = f"the last good checkpoint is {last}" if last else "no checkpoint was written yet"
        raise TrainingDivergedError(f"training diverged: {what}; {where}",
                                    path=self.run_dir.root,
                                    hint="lower the learning rates or check the input images, then resume or restart")

    # --- the loop ------------------------------------------------------------------
    def _start_run_dir(self, resume_state: Optional[dict]) -> None:
        run = self.run_dir
        if resume_state is None:
            if run.exists() and not self.config.resume:
                raise ConfigError("the run folder already holds a run", path=run.root,
                                  hint="pass --resume to continue it, or choose another --out")
            run.root.mkdir(parents=True, exist_ok=True)
            for _, path in list_checkpoints(run.checkpoints):
                path.unlink()  # a fresh start must not resume from an older run's checkpoints later
        # temporary files of a checkpoint write interrupted by SIGKILL or a power cut
        for partial in run.checkpoints.glob(".step_*") if run.checkpoints.is_dir() else ():
            partial.unlink(missing_ok=True)
        save_config(self.config, run.config)

    def _open_progress(self) -> None:
        callbacks: list[Optional[ProgressCallback]] = [self.user_progress]
        paths = {self.run_dir.events.resolve()}
        self._events_files.append(JsonLinesProgress(self.run_dir.events))
        if self.config.events is not None and Path(self.config.events).resolve() not in paths:
            self._events_files.append(JsonLinesProgress(self.config.events))
        self._progress = combine(*callbacks, *self._events_files)

    def _open_scalars(self) -> None:
        """The TensorBoard sink (``config.tensorboard``), once the run's step is known."""
        if self.config.tensorboard is not None:
            # a resumed run hides what an interrupted session wrote after its last checkpoint
            self._scalars = TensorBoardScalars(self.config.tensorboard, purge_step=self.step + 1 if self.step else None)

    def _close_progress(self) -> None:
        for handle in self._events_files:
            handle.close()
        self._events_files = []
        if self._scalars is not None:
            self._scalars.close()
            self._scalars = None

    def _report(self, step: int, started_step: int, context: Optional[StepContext] = None, *,
                kind: str = "progress") -> None:
        elapsed = self._session_elapsed()
        done = step - started_step
        seconds_per_step = elapsed / done if done > 0 else float("nan")
        remaining = self.config.iterations - step
        metrics = {"loss": self.loss_ema if self.loss_ema is not None else float("nan"),
                   "psnr": self.psnr_ema if self.psnr_ema is not None else float("nan"),
                   "n_gaussians": len(self.gaussians),
                   "eta_s": seconds_per_step * remaining if done > 0 else float("nan"),
                   "s_per_step": seconds_per_step}
        self._progress(ProgressEvent(step=step, total=self.config.iterations, stage="train", metrics=metrics, kind=kind))
        if self._scalars is not None and context is not None:
            self._scalars.train_step(step, metrics, loss=context.loss, loss_terms=context.loss_values,
                                     learning_rates={name: self.optimizer.learning_rate(name)
                                                     for name in self.optimizer.groups})

    def run(self) -> TrainResult:
        """Train (or continue) the run and return its result."""
        config = self.config
        # a scene that cannot be read fails here, before the run folder is made (nothing left behind)
        check_scene_folder(config.scene, config.images_dir)
        checkpoint_state = None
        if config.resume:
            checkpoint_state = _resume_state(self.run_dir, config, self.method)
        self._start_run_dir(checkpoint_state)
        self._open_progress()
        try:
            return self._run(checkpoint_state)
        except ESGSError as err:
            self._progress(ProgressEvent(step=self.step, total=config.iterations, stage="train", kind="error",
                                         message=str(err)))
            raise
        finally:
            self._close_progress()

    def _run(self, checkpoint_state: Optional[dict]) -> TrainResult:
        config = self.config
        self._last_checkpoint: Optional[Path] = None
        self.setup(checkpoint_state)
        if checkpoint_state is not None:
            self.message(f"resuming from step {self.step} ({len(self.gaussians)} Gaussians)")
        start_step = self.step
        self._open_scalars()
        self._session_start = time.monotonic()
        self._paused_s = 0.0
        status = "completed"
        saved_step = self.step if checkpoint_state is not None else -1
        stop_files = [path for path in (self.run_dir.stop_request, config.stop_file) if path is not None]
        for path in stop_files:
            Path(path).unlink(missing_ok=True)  # a request left by an earlier session must not stop this one
        with StopRequests() as stop:
            for step in range(start_step + 1, config.iterations + 1):
                context = self.train_step(step)
                if stop.signal_name is None and any(Path(path).exists() for path in stop_files):
                    stop.signal_name = "stop request"
                    for path in stop_files:
                        Path(path).unlink(missing_ok=True)
                if stop.signal_name is not None:
                    self.save_checkpoint()
                    saved_step = step
                    status = "interrupted"
                    self.message(f"{stop.signal_name} received: checkpoint saved at step {step}; resume with --resume")
                    break
                if config.checkpoint_every and step % config.checkpoint_every == 0:
                    self.save_checkpoint()
                    saved_step = step
                if config.eval_every and step % config.eval_every == 0 and step < config.iterations:
                    self._evaluate_during_training(step)
                if step % config.progress_every == 0 or step == config.iterations:
                    self._report(step, start_step, context)
                if config.max_minutes and self._session_elapsed() > config.max_minutes * 60.0:
                    status = "time_limit"
                    self.message(f"max_minutes ({config.max_minutes:g}) reached at step {step}: stopping and evaluating")
                    break
            if saved_step != self.step:
                self.save_checkpoint()
            result = self._finish(status)
        return result

    def _finish(self, status: str) -> TrainResult:
        from ..formats.ply import write_gaussians_ply
        from ..formats.reference_3dgs import cfg_args_text, write_reference_layout

        config = self.config
        train_s = self.elapsed_before_s + self._session_elapsed()
        model = self._exported_model()
        write_gaussians_ply(self.run_dir.point_cloud, model.to_ply())
        write_reference_layout(self.run_dir, self.step, [*self.data.train, *self.data.test], cfg_args=cfg_args_text(
            sh_degree=config.sh_degree, source_path=self.scene, model_path=self.run_dir.root, images=config.images_dir,
            resolution=config.width if config.width > 0 else config.resolution,
            white_background=tuple(config.background) == (1.0, 1.0, 1.0), eval=config.test_every > 0))
        if self.sky is not None:
            save_sky(self.run_dir.sky, self.sky)
        metrics = None
        if status != "interrupted" and config.evaluate:
            metrics = self._evaluate_held_out(
                model, renders_dir=self.run_dir.test_renders if config.save_renders else None,
                use_lpips=config.lpips, progress=self._progress)
            metrics["step"] = self.step
            atomic_write_json(self.run_dir.metrics, metrics)
            if config.eval_every and metrics.get("psnr") is not None:
                self._eval_event(self.step, metrics, train_s)  # the curve's last point
            elif self._scalars is not None:
                self._scalars.evaluation(self.step, metrics)
        elapsed = self.elapsed_before_s + self._session_elapsed()
        result = TrainResult(run_dir=self.run_dir.root, status=status, step=self.step, iterations=config.iterations,
                             n_gaussians=len(self.gaussians), elapsed_s=elapsed, metrics=metrics,
                             point_cloud=self.run_dir.point_cloud, checkpoint=self._last_checkpoint, train_s=train_s)
        atomic_write_json(self.run_dir.result, result.to_dict())
        summary = {"n_gaussians": len(self.gaussians), "elapsed_s": elapsed}
        if metrics:
            summary.update({k: metrics[k] for k in ("psnr", "ssim", "lpips") if metrics.get(k) is not None})
        self._progress(ProgressEvent(step=self.step, total=config.iterations, stage="train", kind="done",
                                     metrics=summary, message=status))
        return result


def _marks_sky(mask_source: Optional[str]) -> bool:
    """Whether the masks of ``mask_source`` mark sky (0 = no surface), not just missing values;
    a folder of another name under priors/ is not assumed to."""
    if mask_source is None or mask_source not in {source.value for source in PriorSource}:
        return False
    return PriorSource(mask_source).masks_sky


def _mean_colour(views: Sequence[View], *, sky: bool) -> Optional[torch.Tensor]:
    """[3] mean colour of the views' pixels that count in the loss (``sky`` False: mask True, or
    every pixel of a view without a mask) or of their sky pixels (``sky`` True: mask False);
    None when there are none."""
    total, count = torch.zeros(3, dtype=torch.float64), 0
    for view in views:
        if view.mask is None:
            pixels = view.image[:0] if sky else view.image
        else:
            keep = view.mask[..., 0].bool()
            pixels = view.image[~keep if sky else keep]
        pixels = pixels.reshape(-1, 3)
        total += pixels.double().sum(dim=0) / 255.0
        count += pixels.shape[0]
    return (total / count).float() if count else None


def _sky_alpha_term(context: LossContext) -> torch.Tensor:
    """Mean alpha over the view's sky pixels (mask False where the source marks sky)."""
    if context.mask is None:
        return context.alpha.sum() * 0.0
    sky = ~context.mask[..., 0]
    if not bool(sky.any()):
        return context.alpha.sum() * 0.0
    return context.alpha[..., 0][sky].mean()


def _is_grey(image: torch.Tensor) -> bool:
    """Whether an [H, W, 3] image has equal channels everywhere (a grey camera stored as RGB)."""
    return bool((image[..., 0] == image[..., 1]).all() and (image[..., 1] == image[..., 2]).all())


def _surface_alpha_term(context: LossContext) -> torch.Tensor:
    """Mean (1 - alpha) over the view's surface pixels (mask True): the sky model shows only
    through sky, so it cannot stand in for half-transparent ground."""
    if context.mask is None:
        return context.alpha.sum() * 0.0
    surface = context.mask[..., 0]
    if not bool(surface.any()):
        return context.alpha.sum() * 0.0
    return (1.0 - context.alpha[..., 0][surface]).mean()


def _resume_state(run: RunDir, config: TrainConfig, method: Method) -> Optional[dict]:
    """The newest readable checkpoint of ``run`` checked against ``config`` (None: start fresh)."""
    found = list_checkpoints(run.checkpoints)
    state = None
    errors = []
    for _, path in reversed(found):
        try:
            state = load_checkpoint(path)
            break
        except CheckpointError as err:  # a damaged newest file falls back to the one before
            errors.append(str(err))
    if state is None:
        if errors:
            raise CheckpointError("no readable checkpoint: " + "; ".join(errors), path=run.checkpoints)
        return None
    changed = changed_settings(config, state["config"], method)
    if changed:
        raise ConfigError(f"cannot resume with different settings ({describe_changes(changed)})", path=run.config,
                          hint="resume with the run's own settings (esgs train reads them from config.json)")
    return state


def changed_settings(config: TrainConfig, saved: dict, method: Method) -> dict[str, tuple[Any, Any]]:
    """The settings that would make ``config`` train differently from a run saved with ``saved``
    (its config.json or a checkpoint's ``config``; settings it predates count with the value
    such runs had): ``{name: (saved value, value in config)}``, :data:`RESUMABLE_SETTINGS`
    left out. ``config.method_config`` must be complete (``method.settings_of``), as the
    trainer holds it; the saved one is completed here."""
    stored = run_config_from_dict(saved)
    if stored.method == method.name:
        stored.method_config = method.settings_of(stored)  # its defaults filled in, as the current config's
    current = config_to_dict(config)
    previous = config_to_dict(stored)
    return {name: (previous.get(name), current[name]) for name in sorted(current)
            if name not in RESUMABLE_SETTINGS and current[name] != previous.get(name)}


def describe_changes(changed: dict[str, tuple[Any, Any]]) -> str:
    """``changed_settings``'s result in words, "name before -> after; ...", a method's own
    settings compared key by key."""
    parts = []
    for name, (before, after) in changed.items():
        if isinstance(before, dict) and isinstance(after, dict):
            parts += [f"{key} {before.get(key)!r} -> {after.get(key)!r}" for key in sorted(set(before) | set(after))
                      if before.get(key) != after.get(key)]
        else:
            parts.append(f"{name} {before!r} -> {after!r}")
    return "; ".join(parts)


def train(config: TrainConfig, progress: Optional[ProgressCallback] = None,
          hooks: Sequence[TrainHook] = (), *, method: Method = PLAIN_3DGS) -> TrainResult:
    """Train Gaussians on ``config.scene`` into ``config.out`` (see :class:`TrainConfig`).

    ``progress`` receives :class:`~esgs.core.progress.ProgressEvent`\\ s (also written to
    RUN/events.jsonl); ``hooks`` are extra :class:`~.hooks.TrainHook`\\ s, called after the
    method's own. ``method`` must be the one ``config.method`` names (plain 3DGS by default;
    :func:`esgs.core.methods.train` looks it up). With ``config.resume`` the newest
    checkpoint in ``config.out`` is continued.
    """
    return Trainer(config, progress=progress, hooks=hooks, method=method).run()
