"""Training: a 3DGS baseline on a COLMAP scene that the ESGS modules extend through hooks.

Public API:

- ``train(config: TrainConfig, progress=None, hooks=()) -> TrainResult``
- ``evaluate_run(run_dir) -> dict`` (metrics.json content)
- ``TrainConfig``, ``TrainHook``, ``StepContext``, ``LossTerm``, ``LossContext``,
  ``GaussianModel``, ``RenderParams``, ``DensifyReport``, ``RunDir``

Submodules import torch; this package's ``__init__`` imports them lazily so that
``esgs train --help`` and the Blender UI stay fast.
"""
from __future__ import annotations

from typing import Any

from .config import TrainConfig

_LAZY = {
    "train": ".trainer", "Trainer": ".trainer", "TrainResult": ".trainer", "TrainingDivergedError": ".trainer",
    "evaluate_run": ".evaluate", "TrainHook": ".hooks", "StepContext": ".hooks", "LossTerm": ".losses",
    "LossContext": ".losses", "GaussianModel": ".gaussians", "RenderParams": ".gaussians",
    "DensifyReport": ".densify", "RunDir": ".run_dir",
}

__all__ = ["TrainConfig", *_LAZY]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(name)
    import importlib

    return getattr(importlib.import_module(module, __name__), name)
