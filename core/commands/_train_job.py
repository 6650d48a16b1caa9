"""The child side of a training job (not a CLI command: the leading underscore keeps it
out of ``esgs --help``): the ``"train"`` entry of :mod:`esgs.core.runtime.entry_points`.

The parent (:class:`esgs.core.jobs.TrainingJob`) writes the run's TrainConfig as JSON; this
reads it back, lets a resumed run keep the settings it was started with (only the
run-control settings may change), and trains with the method-aware entry point. The trainer
watches ``config.stop_file`` itself: on a stop request it saves a checkpoint and ends as
``"interrupted"``.
"""
from __future__ import annotations

from typing import Any

from ..runtime.child import ChildContext


def _methods_api() -> tuple[Any, Any]:
    """``(train, train_config_from_dict)``: the method registry's when it exists, else the trainer's."""
    try:
        from .. import methods  # the method registry (issue 21, item 1)

        return methods.train, methods.train_config_from_dict
    except (ImportError, AttributeError):
        from ..train import train
        from ..train.config import run_config_from_dict

        return train, run_config_from_dict


def child_job(data: dict[str, Any], context: ChildContext) -> dict[str, Any]:
    """Train (or resume) the run that ``data`` (a TrainConfig as a dict) describes.

    Returns the TrainResult's status, step, iterations, Gaussian count, elapsed time and metrics.

    Raises:
        ConfigError, DatasetError, CheckpointError: as the trainer does.
    """
    import dataclasses
    from pathlib import Path

    from ..config import config_to_dict
    from ..train.run_dir import RunDir
    from ..train.trainer import RESUMABLE_SETTINGS

    train, config_from_data = _methods_api()
    data = dict(data)
    # progress goes to the parent's events file through the context, not a second writer
    data["events"] = None
    saved = RunDir(data["out"]).config if data.get("out") else None
    if data.get("resume") and saved is not None and saved.is_file():
        # a resumed run keeps the settings it was started with; only run control may change
        from ..train.config import load_run_config

        base = config_to_dict(load_run_config(saved))
        data = {**base, **{name: value for name, value in data.items() if name in RESUMABLE_SETTINGS},
                "iterations": data.get("iterations", base.get("iterations"))}
    config = config_from_data(data)
    if context.stop_file is not None:
        config = dataclasses.replace(config, stop_file=Path(context.stop_file))
    result = train(config, progress=context.progress)
    return {"status": result.status, "step": result.step, "iterations": result.iterations,
            "n_gaussians": result.n_gaussians, "elapsed_s": result.elapsed_s, "metrics": result.metrics,
            "point_cloud": str(result.point_cloud)}
