"""The NDN weights that ship inside the package, and how a training checkpoint becomes them.

``core/ndn/weights/ndn_mars.pt`` holds the network trained on our synthetic Mars scenes
(see docs/ndn_model_card.md) in half precision: the same checkpoint format as
:func:`.train.save_checkpoint` without the optimiser state, about 5.5 MB. Inference loads
it (cast back to float32) whenever no weights are named: ``esgs priors --method ndn``,
:func:`.infer.write_ndn_priors` and :func:`resolve_default_weights`.
"""
from __future__ import annotations

import os
from pathlib import Path

import torch

from ..errors import CheckpointError
from ..io_utils import atomic_path

SHIPPED_WEIGHTS = Path(__file__).resolve().parent / "weights" / "ndn_mars.pt"
WEIGHTS_ENVIRONMENT_VARIABLE = "ESGS_NDN_WEIGHTS"


def shipped_weights() -> Path:
    """The weights file inside the package; :class:`CheckpointError` when it is missing."""
    if not SHIPPED_WEIGHTS.exists():
        raise CheckpointError("the package's NDN weights are missing", path=SHIPPED_WEIGHTS,
                              hint="reinstall the package, or pass --weights (a model folder from `esgs ndn train`)")
    return SHIPPED_WEIGHTS


def resolve_default_weights(weights: str | Path | None = None) -> Path:
    """What inference loads: ``weights`` when given, else ``$ESGS_NDN_WEIGHTS``, else the shipped file."""
    if weights:
        return Path(weights)
    if os.environ.get(WEIGHTS_ENVIRONMENT_VARIABLE):
        return Path(os.environ[WEIGHTS_ENVIRONMENT_VARIABLE])
    return shipped_weights()


def export_weights(checkpoint: str | Path, out_path: str | Path = SHIPPED_WEIGHTS, *, half: bool = True,
                   provenance: dict | None = None, sampling: dict | None = None) -> Path:
    """Write a checkpoint's weights (no optimiser or random state) as a small inference file:
    its moving average of the weights when it has one, else its raw weights.

    ``half`` stores the floating-point tensors as float16 (loading casts them back to the
    model's float32). ``provenance`` (plain JSON-like data: source checkpoint, data, steps)
    is stored beside the weights. ``sampling`` overrides inference settings of the saved
    diffusion config (``sample_steps``, ``sample_ensemble``, ``sample_reduce``): they travel
    with the weights, so every caller samples the way the weights were scored. Written
    atomically; returns ``out_path``.
    """
    from ..config import config_from_dict
    from .config import NDNConfig
    from .checkpoint import CHECKPOINT_FORMAT, load_checkpoint

    _, _, _, payload = load_checkpoint(checkpoint)
    config = {**payload["config"], "diffusion": {**payload["config"]["diffusion"]}}
    for key, value in (sampling or {}).items():
        if key not in ("sample_steps", "sample_ensemble", "sample_reduce"):
            raise ValueError(f"not a sampling setting: {key!r}")
        config["diffusion"][key] = value
    config_from_dict(NDNConfig, config)  # validates the overrides
    # a checkpoint with a moving average of the weights ships the average (what it was validated with)
    source = payload["ema"]["weights"] if "ema" in payload else payload["model"]
    state = {name: (tensor.half() if half and tensor.is_floating_point() else tensor).contiguous()
             for name, tensor in source.items()}
    slim = {"format": CHECKPOINT_FORMAT, "config": config, "step": int(payload["step"]), "model": state,
            "dtype": "float16" if half else "float32", "weights": "ema" if "ema" in payload else "raw",
            "provenance": dict(provenance or {})}
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_path) as tmp:
        torch.save(slim, tmp)
    return out_path
