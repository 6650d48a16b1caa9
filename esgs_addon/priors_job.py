"""Prior maps from Blender: compute auto (the default), ndn or sfm priors in a separate process.

``auto`` fuses stereo labels, NDN and SfM per pixel (:mod:`esgs.core.priors.auto`), computing
those it lacks; NDN inference takes ~1-2 s per view on a CPU and needs torch, which Blender's
own Python lacks, so the priors are computed by the same child-process runtime as training
(:mod:`esgs.core.runtime`, its ``"priors"`` job). Public entry points (``operators/priors.py`` wraps them):

- :func:`check_scene` - the checks that fail at once, before a process starts;
- :func:`start_priors` - start the job for a scene folder, non-blocking;
- :func:`wait_for_priors` - block with console progress (headless: ``blender -b``);
- :func:`compute_priors` - both: the call a script makes;
- :func:`start_polling` - the UI path: a timer mirrors the job into ``scene.esgs.priors``.

Both writers replace ``SCENE/priors/<method>`` only when every view is done, and a cancel
(the stop file, then SIGTERM) lets them remove their staging folders: a failed or cancelled job leaves the
previous priors, or none.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Optional


from ..core.apps import jobs
from ..core.colmap.io import find_model_dir
from ..core.errors import CheckpointError, ConfigError, DatasetError, ESGSError
from ..core.priors.job import PriorsSettings
from ..core.apps.jobs import ChildJob, JobState
from ..core.formats.scene_dir import PriorSource, SceneDir, names
from . import preferences

METHODS = names(PriorSource.computed())
#: the weights ``esgs priors --method ndn`` loads when none are named; the same path as
#: ``core/ndn/shipped.py``'s SHIPPED_WEIGHTS (a test checks), which cannot be imported here
#: because it imports torch and Blender's Python has none
SHIPPED_NDN_WEIGHTS = Path(__file__).resolve().parents[1] / "core" / "ndn" / "weights" / "ndn_mars.pt"
#: the normals network loaded beside them when no weights are named (``SHIPPED_NORMAL_WEIGHTS``)
SHIPPED_NDN_NORMAL_WEIGHTS = SHIPPED_NDN_WEIGHTS.with_name("ndn_completion.pt")
NDN_WEIGHTS_VARIABLE = "ESGS_NDN_WEIGHTS"
NDN_NORMAL_WEIGHTS_VARIABLE = "ESGS_NDN_NORMAL_WEIGHTS"
#: Tests replace the command prefix (``[python, -m, esgs.core.runtime.child]``) with a fake one.
COMMAND_OVERRIDE: Optional[list[str]] = None


class PriorsJob(ChildJob):
    """The ``"priors"`` job of the child-process runtime for one scene folder and method.

    Its settings are a :class:`esgs.core.priors.job.PriorsSettings`, written as the
    child's config file; progress, cancel (the stop file: the writers remove their staging
    folders) and the failure message are the runtime's. The exchange files and events live
    in a temporary folder (``events_dir``), never in the scene folder; :meth:`cleanup`
    removes it once the job ended.
    """

    task = "priors"

    def __init__(self, scene_dir: str | Path, method: str, *, weights: str | Path | None = None,
                 command: Optional[list[str]] = None, python: Optional[str] = None, threads: int = 0,
                 on_output: Optional[Callable[[str], None]] = None):
        if method not in METHODS:
            raise ConfigError(f"unknown prior method {method!r}", hint=f"choose one of {', '.join(METHODS)}")
        self.scene_dir = Path(scene_dir)
        self.method = method
        self.weights = Path(weights) if weights else None
        self.events_dir = Path(tempfile.mkdtemp(prefix="esgs_priors_"))
        settings = PriorsSettings(scene=self.scene_dir, method=method, weights=self.weights)
        super().__init__("priors", settings, workdir=self.events_dir, command=command, python=python,
                         threads=threads, on_output=on_output)

    @property
    def run_dir(self) -> Path:
        """The temporary folder of the job's files (named like the training job's run folder)."""
        return self.events_dir

    def initial_total(self) -> int:
        return 1  # only until the first event brings the view count

    def cleanup(self) -> None:
        """Remove the temporary events folder (only once the child has ended)."""
        if not self.running:
            shutil.rmtree(self.events_dir, ignore_errors=True)


def job_key(scene_dir: str | Path) -> str:
    """One priors job per scene folder (a key apart from the training job's)."""
    return "priors:" + str(Path(scene_dir).resolve())


def default_ndn_weights(weights: str | Path | None = None) -> Path:
    """What the child will load: ``weights``, else ``$ESGS_NDN_WEIGHTS``, else the shipped file."""
    if weights:
        return Path(weights)
    if os.environ.get(NDN_WEIGHTS_VARIABLE):
        return Path(os.environ[NDN_WEIGHTS_VARIABLE])
    return SHIPPED_NDN_WEIGHTS


def check_scene(scene_dir: str | Path, method: str, weights: str | Path | None = None) -> None:
    """Fail at once, in Blender, for what would make the child fail (no process started).

    Raises:
        DatasetError: the folder, its COLMAP model (sparse/0) or, for ndn, its images/ folder is missing.
        CheckpointError: ``ndn`` and the weights file or folder does not exist.
        ConfigError: an unknown method.
    """
    if method not in METHODS:
        raise ConfigError(f"unknown prior method {method!r}", hint=f"choose one of {', '.join(METHODS)}")
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise DatasetError("the scene folder does not exist", path=scene_dir, hint="choose an existing scene folder")
    # the folders the command reads the model from (sparse/0, sparse, the folder itself);
    # the error names what is missing
    find_model_dir(scene_dir)
    if method == "ndn":
        if not SceneDir(scene_dir).images.is_dir():
            raise DatasetError("the scene folder has no images/ folder (NDN predicts from the images)",
                               path=scene_dir, hint="put the views named in the COLMAP model in SCENE/images")
        path = default_ndn_weights(weights)
        if not path.exists():
            raise CheckpointError("NDN weights not found", path=path,
                                  hint="choose a weights file or model folder, or reinstall the extension "
                                       "(it ships weights)")
        # the shipped depth network comes with the shipped normals network (core/ndn/shipped.py)
        if path == SHIPPED_NDN_WEIGHTS and not os.environ.get(NDN_NORMAL_WEIGHTS_VARIABLE) \
                and not SHIPPED_NDN_NORMAL_WEIGHTS.exists():
            raise CheckpointError("the extension's NDN normal weights are missing", path=SHIPPED_NDN_NORMAL_WEIGHTS,
                                  hint="reinstall the extension (it ships both networks)")


def start_priors(scene_dir: str | Path, method: str = "auto", *, weights: str | Path | None = None,
                 python: Optional[str] = None, threads: Optional[int] = None,
                 on_output: Optional[Callable[[str], None]] = None) -> PriorsJob:
    """Check the scene and start ``esgs priors`` for it in a child process (non-blocking).

    Args:
        scene_dir: the COLMAP scene folder (images/ + sparse/0); priors go to ``priors/<method>``.
        method: ``auto`` (the default: the best of stereo labels, NDN and SfM per pixel, with
            a confidence; what :func:`esgs.core.methods.full_esgs` trains with), ``ndn`` (dense
            relative depth and normals) or ``sfm`` (sparse depth).
        weights: ndn weights file or model folder (default: ``$ESGS_NDN_WEIGHTS``, else shipped).
        python: interpreter (default: the add-on preference, then :func:`esgs.core.apps.jobs.find_python`).
        threads: CPU threads for the child (default: the preference).

    Raises:
        ESGSError: a check failed (:func:`check_scene`), a priors job is already running for
            this scene, or the process could not start.
    """
    scene_dir = Path(scene_dir)
    check_scene(scene_dir, method, weights)
    key = job_key(scene_dir)
    current = jobs.get_job(key)
    if current is not None and current.running:
        raise ESGSError("priors are already being computed for this scene", path=scene_dir,
                        hint="wait for them or cancel them first")
    if current is not None:
        current.cleanup()
    threads = preferences.trainer_threads() if threads is None else threads
    command = list(COMMAND_OVERRIDE) if COMMAND_OVERRIDE else None
    job = PriorsJob(scene_dir, method, weights=weights, command=command,
                    python=None if command else (python or preferences.trainer_python()), threads=threads,
                    on_output=on_output)
    try:
        return jobs.start_job(key, job)
    except BaseException:
        job.cleanup()
        raise


def running_job(scene_dir: str | Path) -> Optional[PriorsJob]:
    """The priors job of ``scene_dir`` while it runs, else None."""
    job = jobs.get_job(job_key(scene_dir))
    return job if job is not None and job.running else None


def wait_for_priors(job: PriorsJob, *, report: Callable[[str], None] = print, interval_s: float = 2.0) -> JobState:
    """Block until ``job`` ends, reporting its progress (one line every ``interval_s``); then
    remove its events folder."""
    last = [0.0]

    def show(state: JobState) -> None:
        now = time.monotonic()
        if now - last[0] >= interval_s or not state.active:
            last[0] = now
            report(f"ESGS priors ({job.method}): {state.summary()}")

    try:
        return job.wait(on_update=show, poll_s=min(0.5, interval_s))
    finally:
        job.cleanup()


def compute_priors(scene_dir: str | Path, method: str = "auto", *, weights: str | Path | None = None,
                   python: Optional[str] = None, threads: Optional[int] = None,
                   report: Callable[[str], None] = print) -> JobState:
    """Compute ``SCENE/priors/<method>`` blocking, with console progress; returns the final
    state (check ``state.status`` and ``state.error``)."""
    job = start_priors(scene_dir, method, weights=weights, python=python, threads=threads)
    return wait_for_priors(job, report=report)


# --------------------------------------------------------------------------- UI state


def copy_state(settings: Any, state: JobState, scene_dir: str | Path | None = None,
               method: str | None = None) -> None:
    """Mirror a job state into ``scene.esgs.priors``."""
    settings.status = state.status
    settings.step = state.step
    settings.total = state.total
    settings.progress = state.fraction
    settings.error = state.error
    if scene_dir is not None:
        settings.last_scene_dir = str(scene_dir)
    if method is not None:
        settings.last_method = method


def start_polling(scene_name: str, key: str) -> None:
    """Follow the priors job of ``key`` with a timer: its state into the scene's
    ``esgs.priors`` settings and the window manager's progress bar (UI only)."""
    from .training_job import follow_job

    def owns(scene: Any, job: PriorsJob) -> bool:
        settings = scene.esgs.priors
        return bool(settings.last_scene_dir) and Path(settings.last_scene_dir) == job.scene_dir \
            and settings.last_method == job.method

    follow_job(scene_name, key, lambda scene, state: copy_state(scene.esgs.priors, state),
               lambda scene, job, state: job.cleanup(), owns=owns)
