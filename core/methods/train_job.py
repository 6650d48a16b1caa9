"""The child side of a training job: the ``"train"`` entry of :mod:`esgs.core.runtime.entry_points`.

The parent (:class:`esgs.core.apps.jobs.TrainingJob`) writes the run's TrainConfig as JSON; this
reads it back, lets a resumed run keep the settings it was started with (only the
run-control settings may change), and trains with the method-aware entry point. The trainer
watches ``config.stop_file`` itself: on a stop request it saves a checkpoint and ends as
``"interrupted"``.
"""
from __future__ import annotations

from typing import Any

from ..runtime.child import ChildContext


def child_job(data: dict[str, Any], context: ChildContext) -> dict[str, Any]:
    """Train (or resume) the run that ``data`` (a TrainConfig as a dict) describes.

    Returns the TrainResult's status, step, iterations, Gaussian count, elapsed time and metrics.

    Raises:
        ConfigError, DatasetError, CheckpointError: as the trainer does.
    """
    import dataclasses
    from pathlib import Path

    from ..config import config_to_dict
    from ..formats.run_dir import RunDir
    from ..train.trainer import RESUMABLE_SETTINGS

    from . import train, train_config_from_dict as config_from_data
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
    # a fresh run is a request (missing settings take today's defaults); a resumed one was
    # completed from its saved config.json above
    config = config_from_data(data, saved=False)
    if context.stop_file is not None:
        config = dataclasses.replace(config, stop_file=Path(context.stop_file))
    progress = context.progress
    if context.events_path is not None and config.out is not None and \
            Path(context.events_path).resolve() == RunDir(Path(config.out)).events.resolve():
        progress = None  # the trainer writes RUN/events.jsonl itself: one writer, no doubled lines
    result = train(config, progress=progress)
    return {"status": result.status, "step": result.step, "iterations": result.iterations,
            "n_gaussians": result.n_gaussians, "elapsed_s": result.elapsed_s, "metrics": result.metrics,
            "point_cloud": str(result.point_cloud)}
