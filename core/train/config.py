"""TrainConfig: every setting of a training run, with the paper's defaults.

All step counts below are given for the paper's 30,000-step schedule. When
``iterations`` differs they are scaled in proportion (:meth:`TrainConfig.scaled_step`),
so a 2,000-step run still warms up its SH degree, densifies, stops densifying and
finishes its learning-rate decay at the same fractions of the run.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from ..config import config_from_dict
from ..errors import ConfigError

#: The schedule every step count of :class:`TrainConfig` is written for.
REFERENCE_ITERATIONS = 30_000

BACKENDS = ("auto", "cpu", "reference", "cuda")
#: ``sky`` values: a learned environment map (train/sky.py), or the constant background (3DGS).
SKY_MODELS = ("envmap", "none")
#: Settings that act only through the sky model (``sky envmap``): a run without one (``--vanilla``,
#: ``--sky none``) cannot depend on them (the CLI refuses them with --vanilla; a saved run without a
#: sky model is not stale for them).
SKY_MODEL_SETTINGS = ("sky_alpha_weight", "sky_smooth_weight", "sky_unseen_weight", "surface_alpha_weight",
                      "sky_degree", "sky_lr", "sky_lr_decay", "sky_grid_rows", "sky_init")
#: Where the sky model starts when the masks mark no sky (``TrainConfig.sky_init``).
SKY_INITS = ("images", "black")
GRAYSCALE_MODES = ("auto", "on", "off")
#: ``densify_gradient`` values: which loss terms' screen-space gradients decide clone/split.
DENSIFY_GRADIENTS = ("photometric", "all")

#: The settings that make a run plain 3DGS as published (``esgs train --vanilla``; the bench's
#: baseline rows): the constant background instead of the sky model, no sky masks (so no
#: sky-alpha term and no prior masks), no pruning by contribution. Every other default is 3DGS's own schedule; the Morton
#: order of the Gaussians (``spatial_order``) changes the memory layout, not the maths.
VANILLA_3DGS: dict = {"sky": "none", "mask_source": "none", "prune_hidden": 0.0}


def _help(text: str, **extra) -> dict:
    return {"help": text, **extra}


@dataclass
class TrainConfig:
    """Settings of one training run (3DGS baseline; ESGS modules add their own through hooks)."""

    # --- input / output -------------------------------------------------------------
    scene: Optional[Path] = field(default=None, metadata=_help("COLMAP scene folder (images/ + sparse/0)"))
    out: Optional[Path] = field(default=None, metadata=_help("run folder to write (RUN/ layout of DESIGN.md)"))
    images_dir: str = field(default="images", metadata=_help("image folder inside the scene"))
    resolution: int = field(default=1, metadata=_help("downscale factor of the images (1 = full size)"))
    width: int = field(default=0, metadata=_help("target image width in pixels; overrides --resolution when > 0"))
    test_every: int = field(default=8, metadata=_help("every Nth image (sorted by name, index %% N == 0) is held out; 0 = no test split"))
    mask_source: str = field(default="auto", metadata=_help(
        "priors/<source>/mask/ to use as sky masks: a source name, 'auto' (gt; else a source whose sky maps mark sky, "
        "such as ndn's; else the first found of labels, ndn; never the sparse sfm masks) or 'none'"))
    mask_photometric: bool = field(default=False, metadata=_help(
        "legacy: masked pixels leave the photometric loss (how runs saved before the sky model trained; "
        "their sky then renders as the background)"))
    background: tuple[float, ...] = field(default=(0.0, 0.0, 0.0), metadata=_help(
        "background colour, RGB in [0, 1], behind the Gaussians when sky is none"))
    sky: str = field(default="envmap", metadata=_help(
        "what is behind the Gaussians: envmap = a learned environment map (the sky, trained by the photometric "
        "loss on every pixel; RUN/sky.json; docs/training.md), none = the constant background (plain 3DGS)",
        choices=SKY_MODELS))
    sky_degree: int = field(default=3, metadata=_help("spherical-harmonics degree of the sky model (0..3)"))
    sky_init: str = field(default="images", metadata=_help(
        "the sky model's starting colour where the mask source marks no sky pixels to start from: images = the "
        "training images' mean colour (what a held-out view shows where it sees ground no training view saw, "
        "when no Gaussian reaches there), black = 3DGS's background (before 2026-12-07)", choices=SKY_INITS))
    sky_grid_rows: int = field(default=0, metadata=_help(
        "rows of a direction grid added to the sky model's harmonics (an equirectangular map of 2 x rows columns, "
        "read bilinearly; local support, so the unseen-sky prior fills unseen directions without moving the rest); "
        "0 = harmonics only"))
    sky_lr: float = field(default=0.05, metadata=_help(
        "Adam learning rate of the sky model (its colour in logit units, its directional bands)"))
    sky_lr_decay: float = field(default=0.2, metadata=_help(
        "the sky model's learning rate at the last step as a share of --sky-lr, reached log-linearly (the positions' "
        "schedule): each step sees one view's sky, so a constant rate leaves the sky jittering around its fit; 1 = "
        "constant"))
    sky_alpha_weight: float = field(default=0.05, metadata=_help(
        "weight of mean(alpha) over sky pixels, where the mask source marks sky (gt, ndn): keeps Gaussians from "
        "painting the sky so the sky model does; 0 = off"))
    sky_smooth_weight: float = field(default=0.0, metadata=_help(
        "weight of the sky model's smoothness prior, the Dirichlet energy of its logit field on the sphere "
        "(sum over SH bands of l(l+1) |c_l|^2): keeps the directions no training view saw near the mean sky "
        "colour unless the data asks for a gradient; 0 = off"))
    sky_unseen_weight: float = field(default=0.0, metadata=_help(
        "weight of the sky model's prior on directions no training ray looked along: their colour follows the "
        "nearest directions seen as sky (train/sky.py UnseenSkyPrior); 0 = off"))
    grayscale: str = field(default="auto", metadata=_help(
        "keep the Gaussians' colours grey (equal SH coefficients in R, G and B) so a panchromatic camera "
        "(Navcam) gives no colour casts: auto = when every training image is grey", choices=GRAYSCALE_MODES))
    surface_alpha_weight: float = field(default=0.0, metadata=_help(
        "weight of mean(1 - alpha) over the pixels such masks mark as surface: keeps the ground opaque so the "
        "sky model shows only through the sky; 0 = off"))

    # --- run control ----------------------------------------------------------------
    iterations: int = field(default=30_000, metadata=_help("training steps"))
    max_minutes: float = field(default=0.0, metadata=_help("safety stop: end training after this many minutes and evaluate (0 = none)"))
    seed: int = field(default=0, metadata=_help("random seed (same seed, same result on the CPU)"))
    threads: int = field(default=0, metadata=_help("CPU threads for torch and the rasterizer (0 = library default)"))
    backend: str = field(default="auto", metadata=_help("rasterizer backend", choices=BACKENDS))
    resume: bool = field(default=False, metadata=_help("continue from the last checkpoint in --out"))
    events: Optional[Path] = field(default=None, metadata=_help("also append progress events to this JSON-lines file"))
    tensorboard: Optional[Path] = field(default=None, metadata=_help(
        "also write TensorBoard scalars into this folder: losses per term, training PSNR, Gaussian count, learning "
        "rates, seconds per step, held-out PSNR/SSIM/LPIPS (needs pip install tensorboard; docs/training.md)"))
    stop_file: Optional[Path] = field(default=None, metadata=_help(
        "stop request: when this file appears the run finishes its step, saves a checkpoint and ends as "
        "'interrupted' (works on every platform; RUN/STOP is always watched too)"))
    checkpoint_every: int = field(default=1000, metadata=_help("steps between checkpoints (not scaled; 0 = only at the end)"))
    keep_checkpoints: int = field(default=2, metadata=_help("checkpoints kept in RUN/checkpoints"))
    progress_every: int = field(default=10, metadata=_help("steps between progress events"))
    eval_every: int = field(default=0, metadata=_help(
        "evaluate the held-out views every K steps (PSNR and SSIM; LPIPS only at the end) and write them to "
        "events.jsonl as 'eval' events with the training seconds so far; evaluation time is not counted as "
        "training time; 0 = off"))
    evaluate: bool = field(default=True, metadata=_help("evaluate on the held-out views at the end"))
    save_renders: bool = field(default=True, metadata=_help("write renders/test/<name>.png beside <name>_gt.png"))
    lpips: bool = field(default=True, metadata=_help("compute LPIPS when its weights are available"))

    # --- model ----------------------------------------------------------------------
    sh_degree: int = field(default=3, metadata=_help("maximum spherical-harmonics degree"))
    sh_increase_every: int = field(default=1000, metadata=_help("steps between SH degree increases (scaled)"))
    init_opacity: float = field(default=0.1, metadata=_help("opacity of the initial Gaussians"))
    random_init_points: int = field(default=10_000, metadata=_help("random Gaussians when the model has no 3D points"))
    init_scale_neighbours: int = field(default=3, metadata=_help("initial scale = mean distance to this many nearest points"))

    # --- optimiser (Adam; lr per parameter group) -------------------------------------
    position_lr_init: float = field(default=1.6e-4, metadata=_help("position lr at the start, times the scene extent"))
    position_lr_final: float = field(default=1.6e-6, metadata=_help("position lr at the end, times the scene extent"))
    position_lr_delay_mult: float = field(default=0.01, metadata=_help("position lr warm-up multiplier (3DGS delay_mult)"))
    position_lr_delay_steps: int = field(default=0, metadata=_help("position lr warm-up length in steps (scaled)"))
    feature_lr: float = field(default=2.5e-3, metadata=_help("lr of the SH DC colour; the higher SH bands use feature_lr / 20"))
    opacity_lr: float = field(default=0.05, metadata=_help("opacity lr (the paper's 3DGS version; newer 3DGS uses 0.025)"))
    scaling_lr: float = field(default=5e-3, metadata=_help("log-scale lr"))
    rotation_lr: float = field(default=1e-3, metadata=_help("quaternion lr"))

    # --- loss -----------------------------------------------------------------------
    lambda_dssim: float = field(default=0.2, metadata=_help("weight of (1 - SSIM); L1 gets 1 - lambda_dssim"))

    # --- densification (3DGS) -------------------------------------------------------
    densify: bool = field(default=True, metadata=_help("adaptive density control: clone, split, prune and opacity resets"))
    densify_from: int = field(default=500, metadata=_help("first densification step (scaled)"))
    densify_until: int = field(default=15_000, metadata=_help("no densification from this step on (scaled)"))
    densify_every: int = field(default=100, metadata=_help("steps between densifications (scaled)"))
    densify_grad_threshold: float = field(default=2e-4, metadata=_help(
        "mean screen-space gradient norm, in 3DGS's NDC units, above which a Gaussian is cloned or split"))
    densify_gradient: str = field(default="all", metadata=_help(
        "which screen-space gradients the clone/split statistic accumulates: all = every loss term (3DGS; with "
        "ESGS the prior losses grow Gaussians where the surface disagrees with the priors, which measured "
        "better: docs/training.md), photometric = only the terms that fit the images (fewer Gaussians)",
        choices=DENSIFY_GRADIENTS))
    percent_dense: float = field(default=0.01, metadata=_help("Gaussians larger than this fraction of the extent are split, smaller ones cloned"))
    prune_opacity: float = field(default=0.005, metadata=_help("prune Gaussians whose opacity is below this"))
    prune_screen_size_px: float = field(default=20.0, metadata=_help("after the first opacity reset, prune Gaussians whose screen radius exceeds this"))
    prune_world_size: float = field(default=0.1, metadata=_help("after the first opacity reset, prune Gaussians larger than this fraction of the extent"))
    prune_hidden: float = field(default=0.1, metadata=_help(
        "at the end of densification, prune the Gaussians hidden in every training view: less than this share "
        "of the light reaches them (their summed blending weight over their unoccluded footprint), so the "
        "images cannot place them (0 = never, as 3DGS; docs/training.md)"))
    opacity_reset_every: int = field(default=3000, metadata=_help("steps between opacity resets (scaled; 0 = never)"))
    opacity_reset_value: float = field(default=0.01, metadata=_help("opacities are clamped to at most this at a reset"))
    min_densify_interval: int = field(default=20, metadata=_help(
        "short runs: the scaled densification interval never falls below this many steps, so each "
        "clone/split decision averages gradients over several views"))
    min_opacity_reset_interval: int = field(default=1000, metadata=_help(
        "short runs: the scaled opacity-reset interval never falls below this many steps (opacities need "
        "hundreds of steps to recover from a reset)"))
    max_gaussians: int = field(default=3_000_000, metadata=_help("growth stops (with one warning) at this many Gaussians"))
    spatial_order: bool = field(default=True, metadata=_help(
        "keep the Gaussians sorted by the Morton (Z-order) code of their centres: sorted once after "
        "initialisation and after every densification, Adam's moments and the densification statistics "
        "moving with them, so GPDFN and the rasterizer read neighbours from nearby memory (same maths, "
        "cache-friendlier; docs/esgs.md)"))

    # --- method ---------------------------------------------------------------------
    method: str = field(default="3dgs", metadata=_help(
        "training method (esgs train --list-methods): 3dgs, esgs, mip-splatting, dropout-gs, pgsr, scaffold-gs"))
    method_config: Any = field(default=None, metadata=_help(
        "the method's settings: its dataclass (e.g. ESGSConfig), a dict of its fields when read from JSON, "
        "or None for its defaults"))

    def validate(self) -> None:
        """Raise ConfigError for out-of-range or inconsistent settings."""
        validate_method = getattr(self.method_config, "validate", None)
        if callable(validate_method):
            validate_method()
        if not isinstance(self.method, str) or not self.method:
            raise ConfigError(f"method must be a method name, got {self.method!r}")
        def positive(name: str, allow_zero: bool = False) -> None:
            value = getattr(self, name)
            if value < 0 or (value == 0 and not allow_zero):
                raise ConfigError(f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {value}")

        for name in ("iterations", "resolution", "sh_increase_every", "densify_every", "keep_checkpoints",
                     "progress_every", "random_init_points", "init_scale_neighbours", "max_gaussians"):
            positive(name)
        for name in ("width", "test_every", "max_minutes", "threads", "checkpoint_every", "eval_every",
                     "opacity_reset_every",
                     "densify_from", "densify_until", "position_lr_delay_steps", "sh_degree", "lambda_dssim",
                     "prune_opacity", "densify_grad_threshold", "prune_hidden"):
            positive(name, allow_zero=True)
        if self.backend not in BACKENDS:
            raise ConfigError(f"backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if self.sh_degree > 3:
            raise ConfigError(f"sh_degree must be at most 3, got {self.sh_degree}")
        if not 0.0 < self.init_opacity < 1.0:
            raise ConfigError(f"init_opacity must be in (0, 1), got {self.init_opacity}")
        if not 0.0 <= self.lambda_dssim <= 1.0:
            raise ConfigError(f"lambda_dssim must be in [0, 1], got {self.lambda_dssim}")
        if len(self.background) != 3:
            raise ConfigError(f"background must have 3 values (RGB), got {len(self.background)}")
        if self.grayscale not in GRAYSCALE_MODES:
            raise ConfigError(f"grayscale must be one of {', '.join(GRAYSCALE_MODES)}, got {self.grayscale!r}")
        if self.densify_gradient not in DENSIFY_GRADIENTS:
            raise ConfigError(f"densify_gradient must be one of {', '.join(DENSIFY_GRADIENTS)}, "
                              f"got {self.densify_gradient!r}")
        if self.sky_init not in SKY_INITS:
            raise ConfigError(f"sky_init must be one of {SKY_INITS}, got {self.sky_init!r}")
        if self.sky not in SKY_MODELS:
            raise ConfigError(f"sky must be one of {', '.join(SKY_MODELS)}, got {self.sky!r}")
        if not 0 <= self.sky_degree <= 3:
            raise ConfigError(f"sky_degree must be in 0..3, got {self.sky_degree}")
        if self.sky_grid_rows < 0 or self.sky_grid_rows == 1 or self.sky_grid_rows > 90:
            raise ConfigError(f"sky_grid_rows must be 0 (no grid) or 2..90, got {self.sky_grid_rows}")
        if not 0.0 < self.sky_lr_decay <= 1.0:
            raise ConfigError(f"sky_lr_decay must be in (0, 1], got {self.sky_lr_decay}")
        for name in ("sky_lr", "sky_alpha_weight", "sky_smooth_weight", "sky_unseen_weight", "surface_alpha_weight"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.test_every == 1:
            raise ConfigError("test_every = 1 would hold out every image", hint="use 0 for no test split, or >= 2")

    # --- schedules ------------------------------------------------------------------
    @property
    def schedule_scale(self) -> float:
        """iterations / 30000: the factor every step-based schedule is multiplied by."""
        return self.iterations / REFERENCE_ITERATIONS

    def scaled_step(self, reference_step: int, *, minimum: int = 0) -> int:
        """A step of the 30,000-step schedule, moved to this run's length (rounded)."""
        return max(minimum, int(round(reference_step * self.schedule_scale)))

    def schedule(self) -> "Schedule":
        """The step-based schedule of this run, scaled to ``iterations``."""
        return Schedule(
            iterations=self.iterations,
            sh_increase_every=self.scaled_step(self.sh_increase_every, minimum=1),
            densify_from=self.scaled_step(self.densify_from),
            # no densification also means no opacity resets: both live in the same window
            densify_until=self.scaled_step(self.densify_until) if self.densify else 0,
            densify_every=max(self.scaled_step(self.densify_every, minimum=1), min(self.min_densify_interval,
                                                                                    self.densify_every)),
            opacity_reset_every=(max(self.scaled_step(self.opacity_reset_every, minimum=1),
                                     min(self.min_opacity_reset_interval, self.opacity_reset_every))
                                 if self.opacity_reset_every else 0),
            position_lr_delay_steps=self.scaled_step(self.position_lr_delay_steps),
        )


#: Settings added after runs had been saved, with the value those older runs were trained
#: with: a run folder or checkpoint whose config lacks one is read with this value, so an
#: older run resumes as it was going (Gaussians in their old order) instead of changing.
#: A dotted name ("esgs.sky_weight") is a setting of a section of the legacy layout below.
PREDATING_VALUES: dict = {"spatial_order": False, "esgs.sky_weight": 0.0, "sky": "none", "mask_photometric": True,
                          "surface_alpha_weight": 0.0, "grayscale": "off", "sky_smooth_weight": 0.0,
                          "sky_unseen_weight": 0.0, "sky_grid_rows": 0, "sky_lr_decay": 1.0,
                          "prune_hidden": 0.0, "sky_init": "black"}
#: The same for the settings of one method, in today's layout (``method_config`` of that method).
PREDATING_METHOD_VALUES: dict = {"esgs": {"normal_render": "composited", "gpdfn_hidden": 16}}

#: Legacy layout (runs saved before methods were registered): the method's settings were
#: the sections "esgs" (ESGSConfig) and "baselines" (Mip-Splatting and DropoutGS switches
#: and settings), and a switch inside them chose the method.
_LEGACY_ESGS_SWITCHES = ("depth", "normal", "consistency")
_LEGACY_BASELINES = {"mip-splatting": ("mip_splatting", ("mip_filter_3d", "mip_filter_2d", "mip_frustum_margin")),
                     "dropout-gs": ("dropout_gs", ("dropout_rate", "dropout_compensate"))}


def vanilla(config: "TrainConfig") -> "TrainConfig":
    """A copy of ``config`` with :data:`VANILLA_3DGS` applied (plain 3DGS as published)."""
    import dataclasses

    return dataclasses.replace(config, **VANILLA_3DGS)


def _legacy_esgs_on(esgs: dict) -> bool:
    """Whether a legacy "esgs" section turned ESGS on (ESGSConfig.enabled of that time)."""
    gpdfn = bool(esgs.get("gpdfn")) and int(esgs.get("fused_k", 3)) > 1
    sky = bool(esgs.get("sky_weight", 0.3)) and bool(esgs.get("priors")) and bool(esgs.get("use_masks", True))
    return any(esgs.get(name) for name in _LEGACY_ESGS_SWITCHES) or gpdfn or sky


def from_legacy_layout(data: dict) -> dict:
    """A TrainConfig dict of the legacy layout in today's (``method`` + ``method_config``);
    a dict of today's layout is returned as it is."""
    if "esgs" not in data and "baselines" not in data:
        return data
    converted = dict(data)
    esgs = converted.pop("esgs", None) or {}
    baselines = converted.pop("baselines", None) or {}
    chosen: list[tuple[str, Any]] = []
    if isinstance(esgs, dict) and _legacy_esgs_on(esgs):
        chosen.append(("esgs", dict(esgs)))
    for name, (switch, fields) in _LEGACY_BASELINES.items():
        if isinstance(baselines, dict) and baselines.get(switch) and \
                (switch != "dropout_gs" or float(baselines.get("dropout_rate", 0.1)) > 0):
            chosen.append((name, {key: baselines[key] for key in fields if key in baselines}))
    if len(chosen) > 1:
        raise ConfigError(f"this run combined the methods {', '.join(name for name, _ in chosen)}, which the trainer "
                          "no longer does", hint="train one method per run (esgs train --method NAME)")
    converted["method"], converted["method_config"] = chosen[0] if chosen else ("3dgs", None)
    return converted


def with_predating_values(data: dict) -> dict:
    """``data`` (a saved TrainConfig dict) in today's layout, with every setting of
    :data:`PREDATING_VALUES` it lacks filled in with the value older runs had."""
    filled = dict(data)
    for name, value in PREDATING_VALUES.items():
        section, _, key = name.rpartition(".")
        if not section:
            filled.setdefault(key, value)
        elif isinstance(filled.get(section), dict) and key not in filled[section]:
            filled[section] = {**filled[section], key: value}
    filled = from_legacy_layout(filled)
    settings = filled.get("method_config")
    if isinstance(settings, dict):
        missing = {key: value for key, value in PREDATING_METHOD_VALUES.get(filled.get("method"), {}).items()
                   if key not in settings}
        filled["method_config"] = {**settings, **missing}
    return filled


def run_config_from_dict(data: dict, *, source: str | Path | None = None) -> TrainConfig:
    """The TrainConfig a run was saved with (config.json or a checkpoint's ``config``), older
    runs included. ``method_config`` stays a dict: the method resolves it
    (:meth:`~.method.Method.settings_of`, or :func:`esgs.core.methods.load_run_config`)."""
    return config_from_dict(TrainConfig, with_predating_values(data), source=source)


def load_run_config(path: str | Path) -> TrainConfig:
    """Read a run's config.json with :func:`run_config_from_dict`."""
    from ..config import read_json_object

    return run_config_from_dict(read_json_object(path, what="run's settings (config.json)"), source=Path(path))


@dataclass(frozen=True)
class Schedule:
    """Step-based schedule of one run, already scaled (see :meth:`TrainConfig.schedule`).

    Steps count from 1 to ``iterations`` like 3DGS's iterations.
    """

    iterations: int
    sh_increase_every: int
    densify_from: int
    densify_until: int
    densify_every: int
    opacity_reset_every: int
    position_lr_delay_steps: int

    def sh_degree_at(self, step: int, max_degree: int) -> int:
        """Active SH degree at ``step``: one more band every ``sh_increase_every`` steps."""
        return min(max_degree, (step - 1) // self.sh_increase_every) if step > 0 else 0

    def is_densify_step(self, step: int) -> bool:
        """Clone/split/prune after this step (3DGS: after densify_from, every densify_every, before densify_until)."""
        return self.densify_from < step < self.densify_until and step % self.densify_every == 0

    def accumulates_gradients(self, step: int) -> bool:
        """Screen-space gradients are collected for densification while densification runs."""
        return step < self.densify_until

    def is_opacity_reset_step(self, step: int) -> bool:
        """Opacities are clamped after this step (only while densifying, as 3DGS)."""
        return bool(self.opacity_reset_every) and step < self.densify_until and step % self.opacity_reset_every == 0

    def prunes_large(self, step: int) -> bool:
        """Screen- and world-size pruning starts after the first opacity reset."""
        return bool(self.opacity_reset_every) and step > self.opacity_reset_every
