"""Training: the 3DGS loop on a COLMAP scene, which methods extend with hooks and a
densification strategy (they are registered above this layer, in :mod:`esgs.core.methods`).

Public API:

- ``train(config: TrainConfig, progress=None, hooks=(), method=PLAIN_3DGS) -> TrainResult``
  (:func:`esgs.core.methods.train` looks ``config.method`` up and calls it)
- ``evaluate_run(run_dir) -> dict`` (metrics.json content)
- ``TrainConfig``, ``TrainHook``, ``RunView``, ``StepContext``, ``LossTerm``, ``LossContext``,
  ``GaussianModel``, ``RenderParams``, ``DensifyReport``, ``Strategy``, ``DefaultStrategy``,
  ``Method``, ``MethodParts``, ``RunDir``

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
    "DensifyReport": ".densify", "RunDir": "..formats.run_dir", "Strategy": ".strategy",
    "DefaultStrategy": ".strategy", "RunView": ".hooks", "Method": ".method", "MethodParts": ".method",
}

__all__ = ["TrainConfig", *_LAZY]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(name)
    import importlib

    return getattr(importlib.import_module(module, __name__), name)
