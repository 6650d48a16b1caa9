"""Run the trainer in a separate process and follow its progress.

Training needs torch and minutes to hours of CPU/GPU time, so Blender never trains in its
own process: :class:`TrainingJob` is the ``"train"`` job of the child-process runtime
(:mod:`esgs.core.runtime`): it writes the run's TrainConfig as a JSON config file, starts
the child, tails the JSON-lines events the trainer writes to ``RUN/events.jsonl`` on a
reader thread, and keeps the latest state for a UI timer or a blocking loop to show.
``cancel()`` writes the stop file, on which the trainer saves a checkpoint (every platform);
``resume()`` starts it again with ``resume=True``.

Plain Python, no bpy: the Blender operators and headless scripts both use it.
"""
from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from ..errors import ConfigError
from ..formats.run_dir import RunDir
from ..runtime.process import (  # noqa: F401 - the job API the add-on and scripts import from here
    ACTIVE_STATUSES,
    CANCELLED,
    FAILED,
    FINISHED,
    PENDING,
    RUNNING,
    ChildJob,
    JobState,
    child_command,
    config_data,
    find_python,
    forget_job,
    format_duration,
    get_job,
    start_job,
    stop_all_jobs,
)

#: the run-folder subfolder of the job's exchange files (config, result, stop request)
JOB_FOLDER = ".job"


def trainer_available() -> bool:
    """Whether the engine's trainer module is installed (``esgs.core.train``)."""
    try:
        return importlib.util.find_spec("..train", __package__) is not None
    except (ImportError, ValueError):
        return False


class TrainingJob(ChildJob):
    """One training run in a child process.

    The child reads ``config`` (a TrainConfig, or a dict of its fields; defaults when None)
    with ``scene``, ``out``, ``iterations``, ``resume`` and ``stop_file`` set from this job.
    A resumed run keeps the settings saved in its ``config.json`` except run control.

    Args:
        scene_dir: the COLMAP scene folder to train on.
        run_dir: where the trainer writes checkpoints and ``point_cloud.ply``.
        iterations: number of training steps.
        config: the training settings (TrainConfig); its scene/out/iterations are replaced.
        events_path: the JSON-lines progress file; ``<run_dir>/events.jsonl`` by default.
        trainer: the command prefix (default ``[python, -m, esgs.core.runtime.child]``);
            tests pass a small fake child script with the same interface.
        python: interpreter for the default command (see :func:`find_python`).
        threads: CPU threads for the child (``OMP_NUM_THREADS`` and friends); 0 keeps the default.
        on_output: called with every line the child prints (stdout and stderr merged).
        env: extra environment variables for the child.
    """

    task = "trainer"

    def __init__(self, scene_dir: str | os.PathLike, run_dir: str | os.PathLike, *, iterations: int,
                 config: Any = None, events_path: str | os.PathLike | None = None,
                 trainer: Sequence[str] | None = None, python: str | None = None, threads: int = 0,
                 on_output: Optional[Callable[[str], None]] = None, env: Optional[dict[str, str]] = None):
        if iterations <= 0:
            raise ConfigError(f"iterations must be positive, got {iterations}")
        self.scene_dir = Path(scene_dir)
        self.run_dir = Path(run_dir)
        self.iterations = int(iterations)
        super().__init__("train", config if config is not None else {}, workdir=self.run_dir / JOB_FOLDER,
                         events_path=events_path or RunDir(self.run_dir).events, command=trainer, python=python,
                         threads=threads, on_output=on_output, env=env)

    def check(self) -> None:
        if not self.scene_dir.exists():
            raise ConfigError("the scene folder does not exist", path=self.scene_dir,
                              hint="import a COLMAP scene or choose its folder")

    def initial_total(self) -> int:
        return self.iterations

    def stopped_early(self) -> bool:
        # the trainer ends a stopped run normally (checkpoint, PLY, a "done" event), so only
        # its result tells a stop from a finished run
        return isinstance(self.result, dict) and self.result.get("status") == "interrupted"

    def config_for_child(self, resume: bool = False) -> dict[str, Any]:
        """The TrainConfig dict the child reads: ``config`` with this job's folders and steps."""
        data = config_data(self.config)
        data.update(scene=str(self.scene_dir), out=str(self.run_dir), iterations=self.iterations, resume=bool(resume),
                    stop_file=str(self.stop_path), threads=self.threads or data.get("threads", 0))
        return data

    def start(self, resume: bool = False) -> "TrainingJob":
        """Start the child process; returns at once. Raises ESGSError if already running."""
        super().start(resume)
        return self

    def resume(self) -> "TrainingJob":
        """Start again from the trainer's last checkpoint."""
        return self.start(resume=True)
