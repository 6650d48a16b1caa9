"""Training the NDN network on shards from :mod:`.data`; checkpoints and weights on disk.

``MODEL_DIR`` layout: ``config.json`` (model, diffusion and training settings),
``checkpoints/step_<n>.pt`` (weights, their exponential moving average, optimiser, random
state, schedule start, CPU time, validation scores; written atomically), ``weights.pt``
(the final averaged weights, what ``esgs priors --method ndn`` loads), ``validation.json``
(the validation score of every checkpoint and the best one) and ``events.jsonl`` when the
CLI runs it.

The learning rate follows :func:`learning_rate_at` (a pure function of the step, so a
resumed run continues the same curve); :class:`WeightAverage` keeps the moving average of
the weights that evaluation, export and inference use (:func:`load_checkpoint` loads it
when a checkpoint has one).
"""
from __future__ import annotations

import copy
import dataclasses
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from ..errors import CheckpointError, ConfigError
from ..io_utils import atomic_write_json
from ..progress import ProgressCallback, ProgressEvent, no_progress
from ..runtime.stop import StopRequests
from .config import NDNConfig, NDNTrainConfig
from .data import LOG_DEPTH_RANGE, centre_as_neighbours, check_disjoint_splits, depth_to_state, load_shards
from .checkpoint import (CHECKPOINT_FORMAT, _read_checkpoint, build_model, checkpoint_config,  # noqa: F401
                         latest_checkpoint, load_checkpoint, resolve_weights, save_checkpoint)
from .model import NDNUNet
from .sky_looks import relight_sky


def learning_rate_at(step: int, config: NDNTrainConfig, start_step: int = 0) -> float:
    """The learning rate of optimiser step ``step`` (1-based, counted over the whole training
    history) for a run whose schedule starts after ``start_step`` and ends at ``config.steps``.

    ``warmup_steps`` rise linearly to ``learning_rate``; then ``constant`` stays there,
    ``linear`` and ``cosine`` fall to ``min_lr_ratio * learning_rate`` at ``config.steps``
    (and stay at that floor past it). A pure function of its arguments, so a resumed run
    continues the same curve.
    """
    peak = config.learning_rate
    floor = config.min_lr_ratio * peak
    done = step - start_step  # steps of this schedule taken, this one included
    if config.warmup_steps and done <= config.warmup_steps:
        return peak * max(done, 0) / config.warmup_steps
    if config.lr_schedule == "constant":
        return peak
    span = max(config.steps - start_step - config.warmup_steps, 1)
    fraction = min(max((done - config.warmup_steps) / span, 0.0), 1.0)
    if config.lr_schedule == "linear":
        return peak - (peak - floor) * fraction
    return floor + (peak - floor) * 0.5 * (1.0 + math.cos(math.pi * fraction))


class WeightAverage:
    """Exponential moving average of a model's weights (evaluated and exported instead of the
    last raw weights, which jitter with every mini-batch).

    After update ``n`` (1-based) the average is ``a <- d_n a + (1 - d_n) w`` with
    ``d_n = min(decay, (1 + n) / (10 + n))``: the warm-up keeps the first updates from being
    dominated by the starting weights (with ``d_1 = 2/11`` the average follows the weights
    closely at first and settles to ``decay`` after ~``10 / (1 - decay)`` updates).
    Integer buffers are copied, not averaged.
    """

    def __init__(self, model: torch.nn.Module, decay: float, updates: int = 0):
        self.decay = float(decay)
        self.updates = int(updates)
        self.weights = {name: tensor.detach().clone() for name, tensor in model.state_dict().items()}

    def decay_at(self, update: int) -> float:
        """``d_n`` of update ``n`` (see the class docstring)."""
        return min(self.decay, (1.0 + update) / (10.0 + update))

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        self.updates += 1
        decay = self.decay_at(self.updates)
        for name, tensor in model.state_dict().items():
            if tensor.is_floating_point():
                self.weights[name].mul_(decay).add_(tensor.detach(), alpha=1.0 - decay)
            else:
                self.weights[name].copy_(tensor)

    def state_dict(self) -> dict:
        return {"decay": self.decay, "updates": self.updates, "weights": self.weights}

    def load_state_dict(self, state: dict) -> None:
        self.decay, self.updates = float(state["decay"]), int(state["updates"])
        self.weights = {name: tensor.detach().clone() for name, tensor in state["weights"].items()}

    def averaged_model(self, model: NDNUNet) -> NDNUNet:
        """A copy of ``model`` holding the averaged weights, in eval mode."""
        averaged = copy.deepcopy(model)
        averaged.load_state_dict(self.weights)
        return averaged.eval()


# the validation score that chooses the checkpoint to ship: each term is 1 at the depth
# targets (AbsRel 0.065, delta1 0.973) and at 20 degrees of mean normal error; lower is better
SELECTION_SCALES = {"abs_rel": 0.065, "one_minus_delta1": 1.0 - 0.973, "normal_mean_deg": 20.0}


def selection_score(scores: dict[str, float]) -> float:
    """One number from mean validation scores (``abs_rel``, ``delta1``, ``normal_mean_deg``); lower is better."""
    return (scores["abs_rel"] / SELECTION_SCALES["abs_rel"]
            + (1.0 - scores["delta1"]) / SELECTION_SCALES["one_minus_delta1"]
            + scores["normal_mean_deg"] / SELECTION_SCALES["normal_mean_deg"])


def validation_subset(arrays: dict[str, np.ndarray], count: int) -> dict[str, np.ndarray]:
    """``count`` triples evenly spaced over ``arrays`` (all of them when ``count`` is 0 or more than there are)."""
    total = arrays["views"].shape[0]
    if not count or count >= total:
        return arrays
    index = np.unique(np.linspace(0, total - 1, count).round().astype(int))
    return {key: value[index] for key, value in arrays.items()}


def best_checkpoint(model_dir: str | Path) -> Path | None:
    """The checkpoint with the lowest validation score in ``MODEL_DIR/validation.json``, or None."""
    path = Path(model_dir) / "validation.json"
    if not path.exists():
        return None
    best = json.loads(path.read_text()).get("best")
    return Path(model_dir) / "checkpoints" / best["checkpoint"] if best else None


def depth_state_of(config: NDNConfig) -> tuple[str, float | None]:
    """What a model's depth state means: (kind, c) for the log state, (kind, None) for affine."""
    kind = config.diffusion.depth_state
    return kind, (config.diffusion.log_depth_range if kind == "log" else None)


def check_same_depth_state(requested: NDNConfig | None, loaded: NDNConfig, path: str | Path, action: str) -> None:
    """Refuse to continue a checkpoint (``action``: "resume" or "fine-tune") with another depth
    state: the network learned to denoise one mapping of depth to [-1, 1], and its samples
    read with another mapping are no longer depth up to scale and shift (affine read as log is
    exponential in depth; log with another c is a power of depth)."""
    if requested is not None and depth_state_of(requested) != depth_state_of(loaded):
        raise ConfigError(f"cannot {action} a checkpoint trained with depth state {depth_state_of(loaded)[0]!r}"
                          f"{_describe_range(loaded)} as depth state {depth_state_of(requested)[0]!r}"
                          f"{_describe_range(requested)}", path=path,
                          hint="train a new model folder from scratch (no --init, no --resume) for another "
                               "depth state, or leave --depth-state/--log-depth-range out to keep the checkpoint's")


def _describe_range(config: NDNConfig) -> str:
    c = depth_state_of(config)[1]
    return "" if c is None else f" (log_depth_range {c:g})"


def resume_source(model_dir: str | Path) -> Path | None:
    """What ``--resume`` continues in ``MODEL_DIR``: the latest checkpoint, else ``weights.pt``, else None."""
    checkpoint = latest_checkpoint(model_dir)
    if checkpoint is None and (Path(model_dir) / "weights.pt").exists():
        checkpoint = Path(model_dir) / "weights.pt"
    return checkpoint


# Training settings that did not exist when some runs were started, with the value those runs
# trained with: a saved config.json without the key resumes with this, not today's default.
SETTINGS_BEFORE_THEY_EXISTED = {"augment": 0.0, "crop_zoom": 0.0, "sky_looks": 0.0, "monocular": 0.0}


def saved_train_config(model_dir: str | Path) -> NDNTrainConfig | None:
    """The training settings a run in ``MODEL_DIR`` was started (or last resumed) with, from its
    ``config.json``; None when there is no such file. ``--resume`` starts from these and lets
    the flags given override them, so a default changed since the run started does not change it."""
    from ..config import config_from_dict

    path = Path(model_dir) / "config.json"
    if not path.is_file():
        return None
    try:
        saved = json.loads(path.read_text(encoding="utf-8"))["train"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ConfigError(f"cannot read the run's training settings: {err}", path=path,
                          hint="restore the file, or start a new model folder without --resume") from err
    return config_from_dict(NDNTrainConfig, {**SETTINGS_BEFORE_THEY_EXISTED, **saved}, source=path)


def training_tensors(arrays: dict[str, np.ndarray], depth_state: str = "affine",
                     log_range: float = LOG_DEPTH_RANGE) -> dict[str, torch.Tensor]:
    """Shard arrays -> network inputs and targets in [-1, 1]: views [N, 9, h, w], depth state
    [N, 1, h, w] (of kind ``depth_state``, see :func:`.data.depth_to_state`), normal state
    [N, 3, h, w] (0 where there is no surface), mask [N, 1, h, w]; also the metric depth
    ``metric`` [N, h, w] and, when the shards have them, the SfM points' depth ``sfm`` [N, h, w]
    (an evidence-conditioned network's targets and evidence are drawn from these per batch)."""
    views = torch.from_numpy(arrays["views"].astype(np.float32) / 127.5 - 1.0)
    depth = np.stack([depth_to_state(d, m, depth_state, log_range)
                      for d, m in zip(arrays["depth"], arrays["mask"])])[:, None]
    normal = arrays["normal"] * arrays["mask"][:, None]
    tensors = {"views": views, "depth": torch.from_numpy(depth.astype(np.float32)),
               "normal": torch.from_numpy(normal.astype(np.float32)),
               "mask": torch.from_numpy(arrays["mask"][:, None].copy()),
               "metric": torch.from_numpy(arrays["depth"].astype(np.float32))}
    if "sfm_depth" in arrays:
        tensors["sfm"] = torch.from_numpy(arrays["sfm_depth"].astype(np.float32))
    if "view_sky" in arrays:
        tensors["view_sky"] = torch.from_numpy(arrays["view_sky"])
    return tensors


def evidence_batch(data: dict[str, torch.Tensor], index: torch.Tensor, flip: bool, config: NDNConfig,
                   generator: torch.Generator) -> dict[str, torch.Tensor]:
    """What an evidence-conditioned or sky-predicting network trains on for the triples ``index``
    (mirrored when ``flip``): the depth state about the drawn evidence's reference, the evidence
    (:func:`.evidence.draw_evidence`) and the sky target (1 = no surface)."""
    from .evidence import draw_evidence, target_state

    metric, mask = data["metric"][index], data["mask"][index, 0]
    sfm = data["sfm"][index] if "sfm" in data else torch.zeros_like(metric)
    if flip:
        metric, mask, sfm = metric.flip(-1), mask.flip(-1), sfm.flip(-1)
    batch: dict[str, torch.Tensor] = {}
    if config.model.sky:
        batch["sky"] = (~mask)[:, None].float()
    if config.model.evidence:
        log_range = config.diffusion.log_depth_range
        evidence, reference, _ = draw_evidence(metric, mask, sfm, generator, log_range)
        batch["evidence"] = evidence
        batch["depth"] = target_state(metric, mask, reference, log_range)
    return batch


def flip_horizontally(views: torch.Tensor, depth: torch.Tensor, normal: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Mirror a batch left-right; a mirrored camera sees normals with x negated."""
    normal = normal.flip(-1).clone()
    normal[:, 0] = -normal[:, 0]
    return views.flip(-1), depth.flip(-1), normal


def crop_and_zoom(views: torch.Tensor, maps: dict[str, torch.Tensor], generator: torch.Generator, *,
                  min_scale: float = 0.6) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Show each triple through a smaller window of its image, zoomed back to the working size.

    Per triple one window (the same for its three views and every per-pixel map), ``min_scale``-1
    of the height and width, anywhere in the image: the horizon lands anywhere in the frame and
    the sky fills a thin band as well as a third of it, as in real rover frames (the generator's
    rover views put it near the middle). Per-pixel camera-frame quantities are unchanged by a crop
    (z depth, normals, sky, evidence), so the maps are resampled, nearest, never blended: a depth
    edge or a point of evidence keeps its values. Views: [B, 9, h, w]; maps: name -> [B, C, h, w].
    """
    batch, _, height, width = views.shape
    uniform = torch.rand((batch, 3), generator=generator)
    scale = min_scale + (1.0 - min_scale) * uniform[:, 0]
    theta = torch.zeros((batch, 2, 3))
    theta[:, 0, 0] = theta[:, 1, 1] = scale
    theta[:, 0, 2] = (2.0 * uniform[:, 1] - 1.0) * (1.0 - scale)  # window centre, in [-1, 1] image units
    theta[:, 1, 2] = (2.0 * uniform[:, 2] - 1.0) * (1.0 - scale)
    grid = F.affine_grid(theta, [batch, 1, height, width], align_corners=False)

    def resample(tensor: torch.Tensor, mode: str) -> torch.Tensor:
        return F.grid_sample(tensor, grid.to(tensor.dtype), mode=mode, padding_mode="border", align_corners=False)

    return resample(views, "bilinear"), {name: resample(value, "nearest") for name, value in maps.items()}


def augment_photometric(views: torch.Tensor, generator: torch.Generator, *, gray_probability: float = 0.3,
                        max_blur_sigma: float = 1.5) -> torch.Tensor:
    """Change how a batch of triples looks, not what it shows: views [B, 9, h, w] in [-1, 1].

    Per triple, the same change for its three views (one camera, one exposure): grey with
    ``gray_probability`` (Navcam-like frames), a gamma in [0.7, 1.4], contrast in [0.7, 1.3] and
    a brightness shift of at most 0.1 (in [0, 1] units), then a Gaussian blur of sigma up to
    ``max_blur_sigma`` px at the working size (a coarse texture seen up close, as on a low-resolution
    terrain model). Depth and normals stay as they are: none of this moves a surface.
    """
    batch = views.shape[0]
    uniform = torch.rand((batch, 5), generator=generator)
    images = ((views.reshape(batch, 3, 3, *views.shape[-2:]) + 1.0) / 2.0).clamp(0.0, 1.0)
    gray = (images * images.new_tensor([0.299, 0.587, 0.114]).view(1, 1, 3, 1, 1)).sum(2, keepdim=True)
    to_gray = (uniform[:, 0] < gray_probability).view(batch, 1, 1, 1, 1)
    images = torch.where(to_gray, gray.expand_as(images), images)
    gamma = (0.7 + 0.7 * uniform[:, 1]).view(batch, 1, 1, 1, 1)
    contrast = (0.7 + 0.6 * uniform[:, 2]).view(batch, 1, 1, 1, 1)
    brightness = (0.2 * uniform[:, 3] - 0.1).view(batch, 1, 1, 1, 1)
    mean = images.mean(dim=(-2, -1), keepdim=True)
    images = images.clamp_min(1e-6) ** gamma
    images = ((images - mean) * contrast + mean + brightness).clamp(0.0, 1.0)
    images = images.reshape(batch, 9, *views.shape[-2:])
    sigmas = max_blur_sigma * uniform[:, 4]
    blurred = [_gaussian_blur(image, float(sigma)) for image, sigma in zip(images, sigmas)]
    return torch.stack(blurred) * 2.0 - 1.0


def _gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of [C, h, w] with reflected borders; sigma below 0.3 px is a no-op."""
    if sigma < 0.3:
        return image
    radius = max(1, int(math.ceil(3.0 * sigma)))
    offsets = torch.arange(-radius, radius + 1, dtype=image.dtype)
    kernel = torch.exp(-0.5 * (offsets / sigma) ** 2)
    kernel = kernel / kernel.sum()
    channels = image.shape[0]
    padded = torch.nn.functional.pad(image[None], (radius, radius, 0, 0), mode="reflect")
    image = torch.nn.functional.conv2d(padded, kernel.view(1, 1, 1, -1).expand(channels, 1, 1, -1), groups=channels)
    padded = torch.nn.functional.pad(image, (0, 0, radius, radius), mode="reflect")
    return torch.nn.functional.conv2d(padded, kernel.view(1, 1, -1, 1).expand(channels, 1, -1, 1), groups=channels)[0]


def _record_validation(out_dir: Path, entry: dict) -> dict:
    """Add one checkpoint's validation scores to ``OUT/validation.json`` (a resumed run replaces
    entries of the steps it repeats) and keep the best one; returns the file's content."""
    path = out_dir / "validation.json"
    record = json.loads(path.read_text()) if path.exists() else {}
    entries = [e for e in record.get("checkpoints", []) if e["step"] != entry["step"]] + [entry]
    entries.sort(key=lambda e: e["step"])
    record = {"selection": "score = AbsRel / 0.065 + (1 - delta1) / 0.027 + normal mean error / 20 deg "
                           "(EMA weights; lower is better)",
              "checkpoints": entries, "best": min(entries, key=lambda e: e["score"])}
    atomic_write_json(path, record)
    return record


def train_ndn(data_dir: str | Path, out_dir: str | Path, train_config: NDNTrainConfig | None = None,
              config: NDNConfig | None = None, *, resume: bool = False,
              progress: ProgressCallback = no_progress) -> dict:
    """Train (or continue training) the NDN network on ``DATA/shards/train_*.npz``.

    With ``resume`` the latest checkpoint in ``OUT/checkpoints`` is loaded (weights, weight
    average, optimiser, random state, schedule start, CPU time, its saved model config) and
    training continues to ``train_config.steps``. Without one, ``train_config.init`` names a
    checkpoint to fine-tune: its raw weights and optimiser moments, its step count (the step
    numbers continue from it, and the learning-rate schedule runs from there to
    ``steps``); the weight average and the batch order start afresh (``seed``). Resuming or
    fine-tuning keeps the checkpoint's model config; a ``config`` with another depth state
    (``depth_state``/``log_depth_range``) is refused with :class:`ConfigError`.

    At every checkpoint the averaged weights are scored on ``DATA``'s validation split
    (``validation_triples`` of it; skipped when there is none) and the scores go into the
    checkpoint, ``OUT/validation.json`` and the progress events. Writes ``OUT/weights.pt``
    (the averaged weights) at the end. Returns a summary dict (``status`` "completed").

    SIGTERM or Ctrl-C (in the main thread) ends the run after the step in progress: a checkpoint
    of that step is saved (without validation), no ``weights.pt`` is written, and the summary's
    ``status`` is "interrupted"; ``resume=True`` continues exactly where it stopped.
    """
    train_config = train_config or NDNTrainConfig()
    train_config.validate()
    out_dir = Path(out_dir)
    (out_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    if train_config.threads:
        torch.set_num_threads(train_config.threads)
    generator = torch.Generator().manual_seed(train_config.seed)
    start_step = 0
    checkpoint = resume_source(out_dir) if resume else None
    lineage: dict = {}
    if checkpoint is not None:
        model, diffusion, loaded, payload = load_checkpoint(checkpoint, ema=False)
        check_same_depth_state(config, loaded, checkpoint, "resume")
        config = loaded
        start_step = int(payload["step"])
        schedule_start = int(payload.get("schedule_start", 0))
        lineage = dict(payload.get("lineage", {}))
    elif train_config.init:
        model, diffusion, loaded, init_payload = load_checkpoint(train_config.init, ema=False)
        check_same_depth_state(config, loaded, train_config.init, "fine-tune")
        config = loaded
        start_step = schedule_start = int(init_payload["step"])
        payload = {"optimizer": init_payload["optimizer"]} if "optimizer" in init_payload else {}
        lineage = {"init_from": str(Path(train_config.init).resolve()), "init_step": start_step}
    else:
        config = config or NDNConfig()
        torch.manual_seed(train_config.seed)
        model, diffusion = build_model(config)
        payload, schedule_start = {}, 0
    if train_config.monocular > 0:  # it learns to read one view alone, so it is fed panoramas that way
        config = dataclasses.replace(config, model=dataclasses.replace(config.model, panorama_input="centre"))
    arrays = load_shards(data_dir, "train", with_view_sky=train_config.sky_looks > 0)
    multiple = 2 ** (config.model.levels - 1)
    if arrays["views"].shape[-1] % multiple or arrays["views"].shape[-2] % multiple:
        raise CheckpointError(f"data resolution {arrays['views'].shape[-1]}x{arrays['views'].shape[-2]} is not a "
                              f"multiple of {multiple} (the model's levels)", path=Path(data_dir))
    has_validation = any((Path(data_dir) / "shards").glob("validation_*.npz"))
    validation = None
    if has_validation:
        check_disjoint_splits(data_dir)  # a score on scenes seen in training would choose nothing
        validation = validation_subset(load_shards(data_dir, "validation"), train_config.validation_triples)
    if config.model.evidence and "sfm_depth" not in arrays:
        raise CheckpointError("an evidence-conditioned network trains on SfM points, and these shards have none",
                              path=Path(data_dir) / "shards",
                              hint="rebuild them with `esgs ndn build-data` (points are on by default) or re-shard the "
                                   "kept scenes with `esgs ndn shard --split train`")
    data = training_tensors(arrays, config.diffusion.depth_state, config.diffusion.log_depth_range)
    optimizer = torch.optim.AdamW(model.parameters(), lr=train_config.learning_rate,
                                  weight_decay=train_config.weight_decay)
    if "optimizer" in payload:
        optimizer.load_state_dict(payload["optimizer"])
        for group in optimizer.param_groups:  # the saved state carries the old run's settings
            group["weight_decay"] = train_config.weight_decay
    if "generator" in payload:
        generator.set_state(payload["generator"])
    average = None
    if train_config.ema_decay > 0:
        average = WeightAverage(model, train_config.ema_decay)
        if "ema" in payload:
            average.load_state_dict(payload["ema"])
            average.decay = train_config.ema_decay
    cpu = dict(payload.get("cpu_seconds", {"train": 0.0, "validation": 0.0}))
    atomic_write_json(out_dir / "config.json", {"ndn": asdict(config), "train": asdict(train_config),
                                                "data": str(data_dir), "schedule_start": schedule_start,
                                                **lineage})
    model.train()
    count = data["views"].shape[0]
    started = time.time()
    run = _TrainingRun(model, diffusion, config, train_config, data, optimizer, generator, average, validation,
                       out_dir, schedule_start, lineage, cpu)
    losses = run.losses
    with StopRequests() as stop:
        step, best = _training_loop(run, start_step, progress, stop)
    if stop.signal_name is not None and step < train_config.steps:
        progress(ProgressEvent(step, train_config.steps, "ndn-train", kind="message",
                               message=f"{stop.signal_name} received: checkpoint saved at step {step}; "
                                       "continue with --resume"))
        summary = {"status": "interrupted", "steps": step, "resumed_from": start_step,
                   "stopped_by": stop.signal_name, "seconds": round(time.time() - started, 1)}
        atomic_write_json(out_dir / "train_summary.json", summary)
        return summary
    model.eval()
    final = average.averaged_model(model) if average is not None else model
    save_checkpoint(out_dir / "weights.pt", final, config, step=step,
                    extra={"weights": "ema" if average is not None else "raw", "lineage": lineage})
    summary = {"status": "completed", "steps": step, "resumed_from": start_step, "train_triples": count,
               "final_loss_mean_last_50": float(np.mean(losses[-50:])) if losses else None,
               "seconds": round(time.time() - started, 1), "cpu_seconds": {k: round(v, 1) for k, v in cpu.items()},
               "best_validation": best, **lineage}
    atomic_write_json(out_dir / "train_summary.json", summary)
    progress(ProgressEvent(step, train_config.steps, "ndn-train", kind="done"))
    return summary


@dataclass
class _TrainingRun:
    """The parts of one :func:`train_ndn` run that its steps and checkpoints share."""

    model: NDNUNet
    diffusion: object
    config: NDNConfig
    train_config: NDNTrainConfig
    data: dict[str, torch.Tensor]
    optimizer: torch.optim.Optimizer
    generator: torch.Generator
    average: "WeightAverage | None"
    validation: dict | None
    out_dir: Path
    schedule_start: int
    lineage: dict
    cpu: dict  # CPU seconds spent on "train" and "validation", carried across resumes
    losses: list[float] = field(default_factory=list)


def _training_loop(run: _TrainingRun, start_step: int, progress: ProgressCallback,
                   stop: StopRequests) -> tuple[int, dict | None]:
    """Steps ``start_step + 1 ..`` of :func:`train_ndn` with its checkpoints; returns (the last step
    taken, the best validation entry). Ends early, after saving a checkpoint of the step it
    finished, when ``stop`` has received a signal."""
    train_config = run.train_config
    started = time.time()
    cpu_mark = time.process_time()
    best = None
    step = start_step
    for step in range(start_step + 1, train_config.steps + 1):
        learning_rate = learning_rate_at(step, train_config, run.schedule_start)
        parts = _take_step(run, learning_rate)
        elapsed = time.time() - started
        eta = elapsed / (step - start_step) * (train_config.steps - step)
        progress(ProgressEvent(step, train_config.steps, "ndn-train",
                               metrics={"loss": run.losses[-1], **parts, "lr": learning_rate, "eta_s": round(eta, 1)}))
        if step % train_config.checkpoint_every == 0 or step == train_config.steps:
            run.cpu["train"] += time.process_time() - cpu_mark
            best = _save_scored_checkpoint(run, step, progress) or best
            cpu_mark = time.process_time()
        if stop.signal_name is not None:
            if step % train_config.checkpoint_every and step != train_config.steps:
                run.cpu["train"] += time.process_time() - cpu_mark
                save_checkpoint(run.out_dir / "checkpoints" / f"step_{step:07d}.pt", run.model, run.config,
                                step=step, optimizer=run.optimizer, generator=run.generator, average=run.average,
                                extra={"schedule_start": run.schedule_start, "lineage": run.lineage,
                                       "cpu_seconds": dict(run.cpu), "stopped_by": stop.signal_name})
            break
    return step, best


def _take_step(run: _TrainingRun, learning_rate: float) -> dict[str, float]:
    """One optimiser step on a random, augmented batch; returns the loss parts (the total is
    appended to ``run.losses``). The draws from ``run.generator`` happen in a fixed order, so a
    resumed run repeats the uninterrupted one."""
    config, train_config, data, generator = run.config, run.train_config, run.data, run.generator
    for group in run.optimizer.param_groups:
        group["lr"] = learning_rate
    count = data["views"].shape[0]
    index = torch.randint(0, count, (min(train_config.batch_size, count),), generator=generator)
    views, depth, normal = data["views"][index], data["depth"][index], data["normal"][index]
    flip = bool(torch.rand((), generator=generator) < 0.5)
    if flip:
        views, depth, normal = flip_horizontally(views, depth, normal)
    if train_config.sky_looks > 0:  # before the photometric change, which may then grey the new sky
        view_sky = data["view_sky"][index]
        views = relight_sky(views, view_sky.flip(-1) if flip else view_sky, generator,
                            probability=train_config.sky_looks)
    if train_config.monocular > 0:  # after the new sky, so the centre that replaces them has it too
        views = centre_as_neighbours(views, torch.rand(views.shape[0], generator=generator) < train_config.monocular)
    if train_config.augment > 0 and bool(torch.rand((), generator=generator) < train_config.augment):
        views = augment_photometric(views, generator)
    extra_inputs: dict[str, torch.Tensor] = {}
    if config.model.evidence or config.model.sky:
        extra_inputs = evidence_batch(data, index, flip, config, generator)
        depth = extra_inputs.pop("depth", depth)
    if train_config.crop_zoom > 0 and bool(torch.rand((), generator=generator) < train_config.crop_zoom):
        views, maps = crop_and_zoom(views, {"depth": depth, "normal": normal, **extra_inputs}, generator)
        depth, normal = maps.pop("depth"), maps.pop("normal")
        extra_inputs = maps
    loss, parts = run.diffusion.training_loss(run.model, views, depth, normal, generator=generator,
                                              normal_weight=train_config.normal_weight,
                                              sky_weight=train_config.sky_weight, **extra_inputs)
    run.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(run.model.parameters(), 1.0)
    run.optimizer.step()
    if run.average is not None:
        run.average.update(run.model)
    run.losses.append(float(loss.detach()))
    return parts


def _save_scored_checkpoint(run: _TrainingRun, step: int, progress: ProgressCallback) -> dict | None:
    """The checkpoint of ``step``, with the averaged weights' validation scores when the data has
    a validation split; returns the best validation entry so far (None without validation)."""
    from .infer import evaluate_arrays, mean_scores  # deferred: inference loads torch models this module trains

    train_config, diffusion = run.train_config, run.diffusion
    extra = {"schedule_start": run.schedule_start, "lineage": run.lineage}
    name = f"step_{step:07d}.pt"
    best = None
    if run.validation is not None:
        now = time.process_time()
        scored = run.average.averaged_model(run.model) if run.average is not None else copy.deepcopy(run.model).eval()
        reduce = diffusion.config.sample_reduce
        diffusion.config.sample_reduce = train_config.validation_reduce or reduce
        scores = mean_scores(evaluate_arrays(scored, diffusion, run.validation, seed=0,
                                             steps=train_config.validation_steps or None,
                                             ensemble=train_config.validation_ensemble or None,
                                             evidence_mode="sfm" if run.config.model.evidence else "none"))
        used_reduce = diffusion.config.sample_reduce
        diffusion.config.sample_reduce = reduce  # the model's own setting stays as saved
        scores["score"] = selection_score(scores)
        extra["validation"] = {**scores, "triples": int(run.validation["views"].shape[0]),
                               "ddim_steps": train_config.validation_steps or diffusion.config.sample_steps,
                               "ensemble": train_config.validation_ensemble or diffusion.config.sample_ensemble,
                               "reduce": used_reduce}
        best = _record_validation(run.out_dir, {"step": step, "checkpoint": name, **extra["validation"]})["best"]
        progress(ProgressEvent(step, train_config.steps, "ndn-validation", metrics=scores, kind="message",
                               message=f"validation at step {step}: " + ", ".join(
                                   f"{key} {value:.4f}" for key, value in scores.items())))
        run.cpu["validation"] += time.process_time() - now
    extra["cpu_seconds"] = dict(run.cpu)
    save_checkpoint(run.out_dir / "checkpoints" / name, run.model, run.config, step=step, optimizer=run.optimizer,
                    generator=run.generator, average=run.average, extra=extra)
    return best
