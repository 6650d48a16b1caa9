"""The NDN weights that ship inside the package, and how a training checkpoint becomes them.

Two networks ship, each in half precision in the checkpoint format of
:func:`.train.save_checkpoint` without the optimiser state (about 5.5 MB each; loading casts
them back to float32):

- ``core/ndn/weights/ndn_mars.pt``, the **depth** network: the diffusion NDN trained on our
  synthetic Mars scenes (docs/ndn_model_card.md);
- ``core/ndn/weights/ndn_completion.pt``, the **normals** network: the evidence-conditioned
  completion network (reads the view's SfM points and stereo labels;
  docs/ndn_completion_model_card.md). Its normals replace the depth network's wherever it
  sees a surface (measured better on every evaluation set, while its depth is not), and its
  sky is written as sky (docs/ndn.md).

``esgs priors --method ndn``, :func:`.infer.write_ndn_priors` and ``priors/auto`` use both
when no weights are named (:func:`resolve_prior_networks`). Naming weights (``--weights`` or
``$ESGS_NDN_WEIGHTS``) means that one network writes depth and normals, unless normal weights
are named too (``--normal-weights`` or ``$ESGS_NDN_NORMAL_WEIGHTS``).
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import torch

from ..errors import CheckpointError
from ..io_utils import atomic_path

SHIPPED_WEIGHTS = Path(__file__).resolve().parent / "weights" / "ndn_mars.pt"
SHIPPED_NORMAL_WEIGHTS = Path(__file__).resolve().parent / "weights" / "ndn_completion.pt"
WEIGHTS_ENVIRONMENT_VARIABLE = "ESGS_NDN_WEIGHTS"
NORMAL_WEIGHTS_ENVIRONMENT_VARIABLE = "ESGS_NDN_NORMAL_WEIGHTS"
#: ``normal_weights`` value that means "the depth network's own normals" (no second network).
SAME_NETWORK = "same"


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


def shipped_normal_weights() -> Path:
    """The normals network inside the package; :class:`CheckpointError` when it is missing."""
    if not SHIPPED_NORMAL_WEIGHTS.exists():
        raise CheckpointError("the package's NDN normal weights are missing", path=SHIPPED_NORMAL_WEIGHTS,
                              hint="reinstall the package, or pass --normal-weights same (the depth network's "
                                   "own normals)")
    return SHIPPED_NORMAL_WEIGHTS


@dataclass(frozen=True)
class PriorNetworks:
    """Which weights write ``priors/ndn``: ``depth`` (depth, mask, and the normals where
    ``normals`` sees no surface) and ``normals`` (None: the depth network's own normals).
    ``default`` says both came from the package (no argument, no environment variable): only
    such priors are rebuilt by ``priors/auto`` when the package's weights change."""

    depth: Path
    normals: Path | None
    default: bool


def resolve_prior_networks(weights: str | Path | None = None,
                           normal_weights: str | Path | None = None) -> PriorNetworks:
    """The networks inference uses (module docstring): named weights first, then the
    environment variables, then the shipped pair. A named depth network without named normal
    weights works alone: a user's own model is not silently mixed with ours."""
    depth_named = bool(weights) or bool(os.environ.get(WEIGHTS_ENVIRONMENT_VARIABLE))
    depth = resolve_default_weights(weights)
    if normal_weights:
        normals = None if str(normal_weights) == SAME_NETWORK else Path(normal_weights)
        return PriorNetworks(depth, normals, default=False)
    environment = os.environ.get(NORMAL_WEIGHTS_ENVIRONMENT_VARIABLE)
    if environment:
        return PriorNetworks(depth, None if environment == SAME_NETWORK else Path(environment), default=False)
    if depth_named:
        return PriorNetworks(depth, None, default=False)
    return PriorNetworks(depth, shipped_normal_weights(), default=True)


def weights_digest(path: str | Path) -> str:
    """A short content hash of a weights file (a model folder: the file it resolves to), so
    priors record which weights made them even when a file is replaced in place."""
    from .checkpoint import resolve_weights

    path = Path(path)
    if path.is_dir():
        path = resolve_weights(path)
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


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
