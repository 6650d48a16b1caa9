"""Training the NDN network on shards from :mod:`.data`; checkpoints and weights on disk.

``MODEL_DIR`` layout: ``config.json`` (model, diffusion and training settings),
``checkpoints/step_<n>.pt`` (weights, optimiser, random state; written atomically),
``weights.pt`` (the final weights, what ``esgs priors --method ndn`` loads) and
``events.jsonl`` when the CLI runs it.
"""
from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from ..config import config_from_dict
from ..errors import CheckpointError
from ..io_utils import atomic_path, atomic_write_json
from ..progress import ProgressCallback, ProgressEvent, no_progress
from .config import NDNConfig, NDNTrainConfig
from .data import depth_to_state, load_shards
from .diffusion import GaussianDiffusion
from .model import NDNUNet

CHECKPOINT_FORMAT = "esgs-ndn-1"


def build_model(config: NDNConfig) -> tuple[NDNUNet, GaussianDiffusion]:
    """The network and diffusion process a config describes."""
    config.validate()
    return NDNUNet(config.model, refine_below=config.diffusion.refine_below), GaussianDiffusion(config.diffusion)


def save_checkpoint(path: str | Path, model: NDNUNet, config: NDNConfig, *, step: int = 0,
                    optimizer: torch.optim.Optimizer | None = None, generator: torch.Generator | None = None,
                    extra: dict | None = None) -> Path:
    """Write weights (plus optimiser and random state when given) to ``path`` atomically."""
    payload = {"format": CHECKPOINT_FORMAT, "config": asdict(config), "step": int(step),
               "model": model.state_dict(), **(extra or {})}
    if optimizer is not None:
        payload["optimizer"] = optimizer.state_dict()
    if generator is not None:
        payload["generator"] = generator.get_state()
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return Path(path)


def load_checkpoint(path: str | Path) -> tuple[NDNUNet, GaussianDiffusion, NDNConfig, dict]:
    """Read a checkpoint or weights file: (model in eval mode, diffusion, config, raw payload)."""
    path = Path(path)
    if path.is_dir():
        path = resolve_weights(path)
    if not path.exists():
        raise CheckpointError("NDN weights file not found", path=path,
                              hint="train weights with `esgs ndn train DATA --out MODEL_DIR`")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises several types for corrupt or foreign files
        raise CheckpointError(f"cannot read NDN weights: {error}", path=path) from error
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError("not an NDN checkpoint (missing or unknown format tag)", path=path)
    config = config_from_dict(NDNConfig, payload["config"])
    model, diffusion = build_model(config)
    try:
        model.load_state_dict(payload["model"])
    except RuntimeError as error:
        raise CheckpointError(f"weights do not match the saved model config: {error}", path=path) from error
    model.eval()
    return model, diffusion, config, payload


def resolve_weights(model_dir: str | Path) -> Path:
    """``MODEL_DIR/weights.pt``, else the latest checkpoint in ``MODEL_DIR/checkpoints``."""
    model_dir = Path(model_dir)
    if (model_dir / "weights.pt").exists():
        return model_dir / "weights.pt"
    latest = latest_checkpoint(model_dir)
    if latest is None:
        raise CheckpointError("no NDN weights in this folder", path=model_dir,
                              hint="expected weights.pt or checkpoints/step_*.pt; train with `esgs ndn train`")
    return latest


def latest_checkpoint(model_dir: str | Path) -> Path | None:
    """The checkpoint with the highest step in ``MODEL_DIR/checkpoints``, or None."""
    paths = sorted(Path(model_dir, "checkpoints").glob("step_*.pt"))
    return paths[-1] if paths else None


def training_tensors(arrays: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """Shard arrays -> network inputs and targets in [-1, 1]: views [N, 9, h, w], depth state
    [N, 1, h, w], normal state [N, 3, h, w] (0 where there is no surface), mask [N, 1, h, w]."""
    views = torch.from_numpy(arrays["views"].astype(np.float32) / 127.5 - 1.0)
    depth = np.stack([depth_to_state(d, m) for d, m in zip(arrays["depth"], arrays["mask"])])[:, None]
    normal = arrays["normal"] * arrays["mask"][:, None]
    return {"views": views, "depth": torch.from_numpy(depth.astype(np.float32)),
            "normal": torch.from_numpy(normal.astype(np.float32)),
            "mask": torch.from_numpy(arrays["mask"][:, None].copy())}


def flip_horizontally(views: torch.Tensor, depth: torch.Tensor, normal: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Mirror a batch left-right; a mirrored camera sees normals with x negated."""
    normal = normal.flip(-1).clone()
    normal[:, 0] = -normal[:, 0]
    return views.flip(-1), depth.flip(-1), normal


def train_ndn(data_dir: str | Path, out_dir: str | Path, train_config: NDNTrainConfig | None = None,
              config: NDNConfig | None = None, *, resume: bool = False,
              progress: ProgressCallback = no_progress) -> dict:
    """Train (or continue training) the NDN network on ``DATA/shards/train_*.npz``.

    With ``resume`` the latest checkpoint in ``OUT/checkpoints`` is loaded (weights,
    optimiser, random state, its saved model config) and training continues to
    ``train_config.steps``. Writes ``OUT/weights.pt`` at the end. Returns a summary dict.
    """
    train_config = train_config or NDNTrainConfig()
    train_config.validate()
    out_dir = Path(out_dir)
    (out_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    if train_config.threads:
        torch.set_num_threads(train_config.threads)
    generator = torch.Generator().manual_seed(train_config.seed)
    start_step = 0
    checkpoint = latest_checkpoint(out_dir) if resume else None
    if resume and checkpoint is None and (out_dir / "weights.pt").exists():
        checkpoint = out_dir / "weights.pt"
    if checkpoint is not None:
        model, diffusion, config, payload = load_checkpoint(checkpoint)
        start_step = int(payload["step"])
    else:
        config = config or NDNConfig()
        torch.manual_seed(train_config.seed)
        model, diffusion = build_model(config)
        payload = {}
    arrays = load_shards(data_dir, "train")
    multiple = 2 ** (config.model.levels - 1)
    if arrays["views"].shape[-1] % multiple or arrays["views"].shape[-2] % multiple:
        raise CheckpointError(f"data resolution {arrays['views'].shape[-1]}x{arrays['views'].shape[-2]} is not a "
                              f"multiple of {multiple} (the model's levels)", path=Path(data_dir))
    data = training_tensors(arrays)
    optimizer = torch.optim.AdamW(model.parameters(), lr=train_config.learning_rate,
                                  weight_decay=train_config.weight_decay)
    if "optimizer" in payload:
        optimizer.load_state_dict(payload["optimizer"])
    if "generator" in payload:
        generator.set_state(payload["generator"])
    atomic_write_json(out_dir / "config.json", {"ndn": asdict(config), "train": asdict(train_config),
                                                "data": str(data_dir)})
    model.train()
    count = data["views"].shape[0]
    started = time.time()
    losses: list[float] = []
    step = start_step
    for step in range(start_step + 1, train_config.steps + 1):
        index = torch.randint(0, count, (min(train_config.batch_size, count),), generator=generator)
        views, depth, normal = data["views"][index], data["depth"][index], data["normal"][index]
        if bool(torch.rand((), generator=generator) < 0.5):
            views, depth, normal = flip_horizontally(views, depth, normal)
        loss, parts = diffusion.training_loss(model, views, depth, normal, generator=generator,
                                              normal_weight=train_config.normal_weight)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        losses.append(float(loss.detach()))
        elapsed = time.time() - started
        eta = elapsed / (step - start_step) * (train_config.steps - step)
        progress(ProgressEvent(step, train_config.steps, "ndn-train",
                               metrics={"loss": losses[-1], **parts, "eta_s": round(eta, 1)}))
        if step % train_config.checkpoint_every == 0 or step == train_config.steps:
            save_checkpoint(out_dir / "checkpoints" / f"step_{step:07d}.pt", model, config, step=step,
                            optimizer=optimizer, generator=generator)
    model.eval()
    save_checkpoint(out_dir / "weights.pt", model, config, step=step)
    summary = {"steps": step, "resumed_from": start_step, "train_triples": count,
               "final_loss_mean_last_50": float(np.mean(losses[-50:])) if losses else None,
               "seconds": round(time.time() - started, 1)}
    atomic_write_json(out_dir / "train_summary.json", summary)
    progress(ProgressEvent(step, train_config.steps, "ndn-train", kind="done"))
    return summary
