"""Settings of the NDN prior network: model size, diffusion schedule, training and sampling."""
from __future__ import annotations

from dataclasses import dataclass, field

from ..errors import ConfigError

# the depth diffusion state: "affine" per view (the shipped weights) or scale-normalised "log"
# depth (see core/ndn/data.py, depth_to_state)
DEPTH_STATES = ("affine", "log")
PANORAMA_INPUTS = ("neighbours", "centre")  # NDNModelConfig.panorama_input


@dataclass
class NDNModelConfig:
    """Size of the UNet noise predictor (defaults: ~2.6M parameters, CPU-sized)."""

    base_channels: int = field(default=32, metadata={"help": "channels of the first UNet level (doubled per level)"})
    levels: int = field(default=3, metadata={"help": "UNet resolution levels (each halves the size)"})
    time_dim: int = field(default=128, metadata={"help": "width of the sinusoidal time-step embedding"})
    working_size: int = field(default=128, metadata={"help": "long side of the working resolution in pixels"})
    evidence: bool = field(default=False, metadata={
        "help": "the network also reads the reference view's metric evidence (SfM points and stereo labels, "
                "4 channels; core/ndn/evidence.py) and predicts depth in metres about it; needs the log depth state"})
    sky: bool = field(default=False, metadata={
        "help": "a sky head: the depth branch also predicts a per-pixel sky logit (trained on the no-surface pixels)"})
    panorama_input: str = field(default="neighbours", metadata={
        "help": "what the network reads as neighbours on a scene shot from one camera centre (a panorama, whose "
                "neighbours are rotations that training never shows): neighbours, or centre (the view itself "
                "three times; set by training with --monocular)"})

    def validate(self) -> None:
        if self.panorama_input not in PANORAMA_INPUTS:
            raise ConfigError(f"panorama_input must be one of {PANORAMA_INPUTS}, got {self.panorama_input!r}")
        if self.base_channels < 4 or self.base_channels % 4:
            raise ConfigError(f"base_channels must be a positive multiple of 4, got {self.base_channels}")
        if not 1 <= self.levels <= 5:
            raise ConfigError(f"levels must be 1..5, got {self.levels}")
        if self.working_size < 16 or self.working_size % (2 ** self.levels):
            raise ConfigError(f"working_size must be >= 16 and a multiple of 2**levels, got {self.working_size}")
        if self.time_dim < 8 or self.time_dim % 2:
            raise ConfigError(f"time_dim must be an even number >= 8, got {self.time_dim}")


@dataclass
class NDNDiffusionConfig:
    """DDPM forward process and DDIM sampling."""

    timesteps: int = field(default=1000, metadata={"help": "diffusion steps T of the forward process"})
    schedule: str = field(default="cosine", metadata={"help": "beta schedule: cosine or linear"})
    prediction: str = field(default="v", metadata={
        "help": "what the network predicts: v (default) or epsilon; 'regression' trains the same network as a "
                "plain one-shot regressor of clean depth and normals (no diffusion; the baseline)"})
    sample_steps: int = field(default=15, metadata={"help": "DDIM steps at inference (eta = 0, deterministic)"})
    sample_ensemble: int = field(default=1, metadata={
        "help": "inference: samples per view from different starting noise, combined by --sample-reduce "
                "(the cost grows with samples x DDIM steps)"})
    sample_reduce: str = field(default="median", metadata={
        "help": "how an ensemble is combined per pixel: median (default) or mean"})
    coarse_fraction: float = field(default=0.5, metadata={
        "help": "normal branch: the noisiest fraction of the T steps (N/T) is denoised coarsely, without "
                "full-resolution image features; the remaining T-N steps fuse them"})
    depth_state: str = field(default="affine", metadata={
        "choices": DEPTH_STATES,
        "help": "what the depth state is: affine (nearest surface -1, farthest +1; what the shipped weights use) "
                "or log (ln(depth / reference) / log_depth_range, clipped to [-1, 1]: precision spread by range); "
                "saved with the weights, inference follows it; checkpoints without it are affine"})
    log_depth_range: float = field(default=2.5, metadata={
        "help": "log state only: the fixed constant c of state = ln(depth / reference) / c; the state covers "
                "reference x e^-c .. reference x e^+c (2.5: a 148x depth ratio around the view's reference)"})

    def validate(self) -> None:
        if self.timesteps < 2:
            raise ConfigError(f"timesteps must be >= 2, got {self.timesteps}")
        if self.schedule not in ("cosine", "linear"):
            raise ConfigError(f"schedule must be cosine or linear, got {self.schedule!r}")
        if self.prediction not in ("epsilon", "v", "regression"):
            raise ConfigError(f"prediction must be epsilon, v or regression, got {self.prediction!r}")
        if not 1 <= self.sample_steps <= self.timesteps:
            raise ConfigError(f"sample_steps must be in 1..timesteps, got {self.sample_steps}")
        if self.sample_ensemble < 1:
            raise ConfigError(f"sample_ensemble must be >= 1, got {self.sample_ensemble}")
        if self.sample_reduce not in ("median", "mean"):
            raise ConfigError(f"sample_reduce must be median or mean, got {self.sample_reduce!r}")
        if not 0.0 <= self.coarse_fraction < 1.0:
            raise ConfigError(f"coarse_fraction must be in [0, 1), got {self.coarse_fraction}")
        if self.depth_state not in DEPTH_STATES:
            raise ConfigError(f"depth_state must be affine or log, got {self.depth_state!r}")
        if not 0.0 < self.log_depth_range <= 10.0:
            raise ConfigError(f"log_depth_range must be in (0, 10], got {self.log_depth_range}")

    @property
    def refine_below(self) -> int:
        """Time steps ``t < refine_below`` are the last T-N steps (fine normals)."""
        return int(round(self.timesteps * (1.0 - self.coarse_fraction)))


@dataclass
class NDNTrainConfig:
    """One training run of the NDN network."""

    steps: int = field(default=2000, metadata={"help": "optimiser steps in total (a resumed run continues to this)"})
    batch_size: int = field(default=8, metadata={"help": "training triples per step"})
    learning_rate: float = field(default=2e-4, metadata={"help": "AdamW learning rate"})
    weight_decay: float = field(default=1e-4, metadata={"help": "AdamW weight decay"})
    normal_weight: float = field(default=1.0, metadata={"help": "weight of the normal branch loss"})
    sky_weight: float = field(default=0.1, metadata={
        "help": "weight of the sky head's cross-entropy (networks with --sky only)"})
    checkpoint_every: int = field(default=200, metadata={"help": "steps between checkpoints"})
    seed: int = field(default=0, metadata={"help": "seed of batches, noise and initial weights"})
    threads: int = field(default=0, metadata={"help": "torch threads (0 = torch's default)"})
    lr_schedule: str = field(default="cosine", metadata={
        "help": "learning rate over the run: constant, linear or cosine (decay from --learning-rate to "
                "--min-lr-ratio x it between the run's first step and --steps)"})
    warmup_steps: int = field(default=0, metadata={"help": "linear warm-up steps at the start of the schedule"})
    min_lr_ratio: float = field(default=0.1, metadata={"help": "floor of the decaying schedules, as a fraction of "
                                                               "--learning-rate"})
    ema_decay: float = field(default=0.999, metadata={
        "help": "decay of the exponential moving average of the weights (0 = none); the average is saved in "
                "checkpoints and is what evaluation, export and weights.pt use"})
    validation_triples: int = field(default=24, metadata={
        "help": "validation triples scored (with the EMA weights) at each checkpoint, evenly spaced over "
                "DATA's validation split (0 = all; skipped when DATA has no validation shards)"})
    validation_steps: int = field(default=0, metadata={
        "help": "DDIM steps of the validation scoring (0 = the model's --sample-steps)"})
    validation_ensemble: int = field(default=0, metadata={
        "help": "samples per view of the validation scoring (0 = the model's --sample-ensemble)"})
    validation_reduce: str = field(default="", metadata={
        "help": "how the validation ensemble is combined: median or mean ('' = the model's --sample-reduce)"})
    augment: float = field(default=0.0, metadata={
        "help": "probability that a batch's views are changed photometrically (grey, gamma, contrast, brightness, "
                "blur; the same for a triple's three views, depth and normals untouched): robustness to cameras and "
                "terrain textures unlike the generator's; 0 = off (the runs before it existed)"})
    crop_zoom: float = field(default=0.5, metadata={
        "help": "probability that a batch's triples are each seen through a window of 60-100 %% of the image, zoomed "
                "back (the same window for a triple's views, targets and evidence): horizons and sky bands anywhere "
                "in the frame; 0 = off (runs saved before it existed resume with 0)"})
    sky_looks: float = field(default=0.5, metadata={
        "help": "probability that a triple's sky is repainted (any brightness from dim to clipped white, grey or "
                "tinted, a gradient and sometimes glare; one colour for its three views): the sky head learns where "
                "the sky is rather than the generator's sky colour; 0.5 (the shipped normals network's fine-tune, docs/ndn.md); "
                "0 = off (runs saved before it existed resume with 0)"})
    monocular: float = field(default=0.3, metadata={
        "help": "probability that a triple's two neighbours are replaced by its centre view (no parallax): the "
                "network learns to read one view alone, and reads scenes shot from one camera centre that way "
                "(its panorama_input becomes centre); 0.3 (the shipped normals network's fine-tune, docs/ndn.md); 0 = off "
                "(runs saved before it existed resume with 0)"})
    init: str = field(default="", metadata={
        "help": "fine-tune: start from this checkpoint's weights and optimiser moments (steps continue from "
                "its step; the schedule spans from there to --steps); ignored when --resume finds a checkpoint"})

    def validate(self) -> None:
        for name in ("steps", "batch_size", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)}")
        if self.learning_rate <= 0:
            raise ConfigError(f"learning_rate must be positive, got {self.learning_rate}")
        if self.lr_schedule not in ("constant", "linear", "cosine"):
            raise ConfigError(f"lr_schedule must be constant, linear or cosine, got {self.lr_schedule!r}")
        if min(self.warmup_steps, self.validation_triples, self.validation_steps, self.validation_ensemble) < 0:
            raise ConfigError("warmup_steps and the validation settings must not be negative")
        if self.validation_reduce not in ("", "median", "mean"):
            raise ConfigError(f"validation_reduce must be median, mean or empty, got {self.validation_reduce!r}")
        if not 0.0 <= self.min_lr_ratio <= 1.0:
            raise ConfigError(f"min_lr_ratio must be in [0, 1], got {self.min_lr_ratio}")
        if not 0.0 <= self.augment <= 1.0:
            raise ConfigError(f"augment must be a probability in [0, 1], got {self.augment}")
        if not 0.0 <= self.monocular <= 1.0:
            raise ConfigError(f"monocular must be a probability in [0, 1], got {self.monocular}")
        if not 0.0 <= self.sky_looks <= 1.0:
            raise ConfigError(f"sky_looks must be a probability in [0, 1], got {self.sky_looks}")
        if not 0.0 <= self.crop_zoom <= 1.0:
            raise ConfigError(f"crop_zoom must be a probability in [0, 1], got {self.crop_zoom}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ConfigError(f"ema_decay must be in [0, 1), got {self.ema_decay}")


@dataclass
class NDNDataConfig:
    """What ``esgs ndn build-data`` renders and stores."""

    scenes: int = field(default=12, metadata={"help": "training scenes to render"})
    heldout: int = field(default=1, metadata={"help": "held-out scenes (seeds never used in training)"})
    validation: int = field(default=0, metadata={
        "help": "validation scenes (training presets, seeds 50000+: never in training or held out); "
                "`esgs ndn train` scores them at each checkpoint to choose the step to ship"})
    presets: tuple[str, ...] = field(default=("cratered_plain", "crater_survey_nadir", "dune_field", "layered_outcrop",
                                              "rocky_slope", "navcam_panorama"),
                                     metadata={"help": "training presets, cycled (default: all without sky)"})
    heldout_presets: tuple[str, ...] = field(default=(), metadata={"help": "presets used only for held-out scenes"})
    views: int = field(default=8, metadata={"help": "views per scene"})
    width: int = field(default=160, metadata={"help": "render width in pixels"})
    height: int = field(default=90, metadata={"help": "render height in pixels"})
    samples: int = field(default=8, metadata={"help": "Cycles samples per pixel"})
    working_size: int = field(default=128, metadata={"help": "long side of the stored triples in pixels"})
    multiple: int = field(default=4, metadata={"help": "stored sizes are multiples of this (2**(levels-1))"})
    keep_scenes: bool = field(default=False, metadata={"help": "keep the rendered scene folders under OUT/scenes"})
    sfm_points: bool = field(default=True, metadata={
        "help": "triangulate each scene's images with its known poses and store the points' depth in the shard "
                "(the evidence an evidence-conditioned network reads; ~2 s per 8-view scene)"})
    palette: str = field(default="varied", metadata={
        "help": "the scenes' look: mars (the generator's fixed sky and ground colours) or varied (drawn from each "
                "scene's seed: sky butterscotch to grey, brightness, haze; ground saturation), so the sky head "
                "does not learn one pairing of sky and ground", "choices": ("mars", "varied")})

    def validate(self) -> None:
        from ..terrain.palette import PALETTES

        if self.palette not in PALETTES:
            raise ConfigError(f"palette must be one of {', '.join(PALETTES)}, got {self.palette!r}")
        for name in ("scenes", "heldout", "validation"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must not be negative, got {getattr(self, name)}")
        for name in ("views", "width", "height", "samples", "working_size", "multiple"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)}")
        if not self.presets:
            raise ConfigError("at least one training preset is needed")
        leaked = sorted(set(self.presets) & set(self.heldout_presets))
        if leaked:
            raise ConfigError(f"held-out presets {leaked} are also training presets")


@dataclass
class NDNConfig:
    """Model and diffusion settings saved with the weights (what inference needs)."""

    model: NDNModelConfig = field(default_factory=NDNModelConfig)
    diffusion: NDNDiffusionConfig = field(default_factory=NDNDiffusionConfig)

    def validate(self) -> None:
        self.model.validate()
        self.diffusion.validate()
        if self.model.evidence and self.diffusion.depth_state != "log":
            raise ConfigError("an evidence-conditioned network needs the log depth state (--depth-state log): its "
                              "output is metric about the evidence's reference depth")
