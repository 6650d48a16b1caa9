"""Checkpoints: one ``torch.save`` file per saved step, written atomically, last K kept.

A checkpoint holds everything needed to continue bit-for-bit: the step, the Gaussian
parameters, Adam's moments, densification statistics, every random generator's state
(torch, the view sampler's numpy generator) and the state of each hook. Files are named
``step_<000123>.pt`` so lexical order is step order. They are loaded with
``weights_only=True``: plain tensors, numbers, strings, lists and dicts only.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Optional

import torch

from ..errors import CheckpointError
from ..io_utils import atomic_path

_NAME = re.compile(r"^step_(\d+)\.pt$")


def checkpoint_path(folder: str | Path, step: int) -> Path:
    return Path(folder) / f"step_{step:09d}.pt"


def list_checkpoints(folder: str | Path) -> list[tuple[int, Path]]:
    """(step, path) of every complete checkpoint in ``folder``, oldest first."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = []
    for path in folder.iterdir():
        match = _NAME.match(path.name)
        if match and path.is_file():
            found.append((int(match.group(1)), path))
    return sorted(found)


def latest_checkpoint(folder: str | Path) -> Optional[Path]:
    found = list_checkpoints(folder)
    return found[-1][1] if found else None


def save_checkpoint(folder: str | Path, step: int, state: dict[str, Any], *, keep: int = 2) -> Path:
    """Write ``state`` for ``step`` atomically (temp file + fsync + rename); keep the newest ``keep``."""
    import os

    path = checkpoint_path(folder, step)
    try:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as handle:
                torch.save(state, handle)
                handle.flush()
                os.fsync(handle.fileno())
    except OSError as err:
        raise CheckpointError(f"cannot write checkpoint: {err}", path=path, hint="is the disk full?") from err
    for _, old in list_checkpoints(folder)[:-keep] if keep > 0 else []:
        old.unlink(missing_ok=True)
    return path


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` (tensors are loaded on the CPU)."""
    path = Path(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError as err:
        raise CheckpointError("checkpoint not found", path=path) from err
    except Exception as err:  # noqa: BLE001 - torch raises many kinds for a damaged file
        raise CheckpointError(f"cannot read checkpoint: {err}", path=path,
                              hint="delete it to resume from the previous one") from err
    if not isinstance(state, dict) or "step" not in state:
        raise CheckpointError("not a training checkpoint", path=path)
    return state
