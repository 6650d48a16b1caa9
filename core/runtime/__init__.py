"""One child-process runtime for every long job (training, priors, labels, Blender renders).

The lowest application layer: it imports only :mod:`esgs.core.errors`,
:mod:`esgs.core.progress`, :mod:`esgs.core.config`, :mod:`esgs.core.io_utils` and the
standard library. A parent starts a registered job (:mod:`.entry_points`) with its settings
dataclass written as a JSON config file (:class:`.process.ChildJob`, or blocking
:func:`.process.run_job`); the child (:mod:`.child`) runs the job's function, sends
progress as JSON-lines :class:`esgs.core.progress.ProgressEvent` and a handled error as our
error type; cancelling writes a stop file (every platform) before it terminates.
"""
from __future__ import annotations

from .child import ChildContext, error_from_dict, error_to_dict
from .entry_points import ENTRY_POINTS, EntryPoint, entry_point
from .process import (
    ACTIVE_STATUSES,
    CANCELLED,
    FAILED,
    FINISHED,
    PENDING,
    RUNNING,
    ChildJob,
    JobState,
    child_command,
    find_python,
    format_duration,
    forget_job,
    get_job,
    run_job,
    start_job,
    stop_all_jobs,
)

__all__ = [
    "ACTIVE_STATUSES", "CANCELLED", "ChildContext", "ChildJob", "ENTRY_POINTS", "EntryPoint", "FAILED", "FINISHED",
    "JobState", "PENDING", "RUNNING", "child_command", "entry_point", "error_from_dict", "error_to_dict",
    "find_python", "format_duration", "forget_job", "get_job", "run_job", "start_job", "stop_all_jobs",
]
