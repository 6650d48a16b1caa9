"""NDN weights and checkpoints on disk: build the network a config describes, write and read
checkpoint files (atomically), find a model folder's weights.

Apart from :mod:`.train` so inference (:mod:`.infer`) and the shipped weights
(:mod:`.shipped`) read weights without importing the trainer, which imports inference to
score validation.
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from ..config import config_from_dict
from ..errors import CheckpointError
from ..io_utils import atomic_path
from .config import NDNConfig
from .diffusion import GaussianDiffusion
from .model import NDNUNet

if TYPE_CHECKING:
    from .train import WeightAverage

CHECKPOINT_FORMAT = "esgs-ndn-1"


def build_model(config: NDNConfig) -> tuple[NDNUNet, GaussianDiffusion]:
    """The network and diffusion process a config describes."""
    config.validate()
    return NDNUNet(config.model, refine_below=config.diffusion.refine_below), GaussianDiffusion(config.diffusion)


def save_checkpoint(path: str | Path, model: NDNUNet, config: NDNConfig, *, step: int = 0,
                    optimizer: torch.optim.Optimizer | None = None, generator: torch.Generator | None = None,
                    average: "WeightAverage | None" = None, extra: dict | None = None) -> Path:
    """Write weights (plus optimiser, random state and weight average when given) to ``path`` atomically."""
    payload = {"format": CHECKPOINT_FORMAT, "config": asdict(config), "step": int(step),
               "model": model.state_dict(), **(extra or {})}
    if optimizer is not None:
        payload["optimizer"] = optimizer.state_dict()
    if generator is not None:
        payload["generator"] = generator.get_state()
    if average is not None:
        payload["ema"] = average.state_dict()
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return Path(path)


def _read_checkpoint(path: str | Path) -> tuple[Path, dict, NDNConfig]:
    """(file, raw payload, saved config) of a checkpoint, weights file or model folder."""
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
    # settings added later (e.g. depth_state) take their defaults in older files: affine
    return path, payload, config_from_dict(NDNConfig, payload["config"])


def load_checkpoint(path: str | Path, *, ema: bool = True) -> tuple[NDNUNet, GaussianDiffusion, NDNConfig, dict]:
    """Read a checkpoint or weights file: (model in eval mode, diffusion, config, raw payload).

    With ``ema`` (the default, what evaluation and inference want) the model holds the
    checkpoint's moving average of the weights when it has one, else its raw weights; the
    trainer resumes with ``ema=False`` (raw weights; the average is in ``payload["ema"]``).
    """
    path, payload, config = _read_checkpoint(path)
    model, diffusion = build_model(config)
    state = payload["ema"]["weights"] if ema and "ema" in payload else payload["model"]
    try:
        model.load_state_dict(state)
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


def checkpoint_config(path: str | Path) -> NDNConfig:
    """The model and diffusion settings saved in a checkpoint or weights file (no model built).
    Files written before ``depth_state`` existed read as the affine state."""
    return _read_checkpoint(path)[2]


def latest_checkpoint(model_dir: str | Path) -> Path | None:
    """The checkpoint with the highest step in ``MODEL_DIR/checkpoints``, or None."""
    paths = sorted(Path(model_dir, "checkpoints").glob("step_*.pt"))
    return paths[-1] if paths else None
