"""Job states saved in a .blend that no job stands behind anymore.

``scene.esgs.training`` and ``scene.esgs.priors`` keep the last known state of their
background job, and a .blend saved while a job ran stores "running". Jobs belong to the
Blender session that started them (their child processes are stopped when it exits), so
when such a file is opened later the panel would show a job that no longer exists, with
no way to start a new one. A ``load_post`` handler corrects that on every file load:

- a job this session knows (same scene folder and run folder or method) has its current
  state copied in, finished or not;
- otherwise the state becomes :data:`INTERRUPTED`, with a message saying what happened and
  what to do: resume the training (``--resume`` continues from its last checkpoint; the
  trainer saves one when Blender stops it), or compute the priors again (an unfinished
  priors job writes nothing).
"""
from __future__ import annotations

from typing import Any, Iterable, Optional

import bpy
from bpy.app.handlers import persistent

from ..core.apps import jobs
from . import priors_job, training_job
from ._registry import file_load_hooks

#: status of a job whose saved state said it ran, but which this Blender session never started
INTERRUPTED = "interrupted"

_ENDED = "was not running anymore when the file was opened (the Blender session that ran it has ended)"
TRAINING_MESSAGE = f"This training {_ENDED}. Press Resume Training to continue it from its last checkpoint."
TRAINING_MESSAGE_NO_RUN = f"This training {_ENDED}. Press Train to start it again."
PRIORS_MESSAGE = (f"This priors job {_ENDED}; an unfinished job writes nothing. "
                  "Press Compute Priors to run it again.")


def _known_training_job(settings: Any) -> Optional[jobs.TrainingJob]:
    """This session's training job of the saved scene and run folders, or None."""
    if not settings.last_scene_dir:
        return None
    job = jobs.get_job(training_job.job_key(settings.last_scene_dir))
    if job is None or not settings.last_run_dir or str(job.run_dir) != settings.last_run_dir:
        return None  # another run of the same scene folder says nothing about the saved one
    return job


def _known_priors_job(settings: Any) -> Optional[jobs.TrainingJob]:
    """This session's priors job of the saved scene folder and method, or None."""
    if not settings.last_scene_dir:
        return None
    job = jobs.get_job(priors_job.job_key(settings.last_scene_dir))
    if job is None or getattr(job, "method", None) != settings.last_method:
        return None
    return job


def update_saved_job_states(scenes: Iterable[bpy.types.Scene]) -> list[str]:
    """Correct the saved training and priors states of ``scenes`` that claim a job is active.

    A job this session knows gives its current state; any other active-looking state
    becomes :data:`INTERRUPTED` with a message (the last step and total are kept, so the
    panel still tells how far it got). Returns ``"<scene name>: training|priors"`` for each
    state set to interrupted.
    """
    interrupted: list[str] = []
    for scene in scenes:
        settings = getattr(scene, "esgs", None)
        if settings is None:
            continue
        training = settings.training
        if training.status in jobs.ACTIVE_STATUSES:
            job = _known_training_job(training)
            if job is not None:
                training_job.copy_state(training, job.state())
            else:
                training.status = INTERRUPTED
                training.eta_s = -1.0
                training.error = TRAINING_MESSAGE if training.last_run_dir else TRAINING_MESSAGE_NO_RUN
                interrupted.append(f"{scene.name}: training")
        priors = settings.priors
        if priors.status in jobs.ACTIVE_STATUSES:
            job = _known_priors_job(priors)
            if job is not None:
                priors_job.copy_state(priors, job.state())
            else:
                priors.status = INTERRUPTED
                priors.error = PRIORS_MESSAGE
                interrupted.append(f"{scene.name}: priors")
    return interrupted


@persistent
def on_file_loaded(*_args: Any) -> None:
    """``load_post`` handler: :func:`update_saved_job_states` for every scene of the new file."""
    for entry in update_saved_job_states(bpy.data.scenes):
        print(f"ESGS: {entry} job was not running anymore; marked {INTERRUPTED}", flush=True)


register_hooks, unregister_hooks = file_load_hooks(on_file_loaded)
