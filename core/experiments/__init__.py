"""Experiment drivers: the paper's ablation grid (``esgs ablate``) and the method comparison
(``esgs bench``). Both are lists of :class:`~.runs.RunTask` (one training run each, in its own
folder, skipped when finished) executed by an :class:`~.executor.Executor` and summarised by
:mod:`.tables`. See docs/experiments.md.
"""
from .runs import RunTask, run_task

__all__ = ["RunTask", "run_task"]
