"""Training from Blender: start the trainer in a separate process and follow it.

Public entry points (the operators in ``operators/train.py`` are thin wrappers):

- :func:`find_scene_dir` - which scene folder to train on;
- :func:`start_training` - start (or resume) the job of a scene folder, non-blocking;
- :func:`wait_for_training` - block with console progress (headless: ``blender -b``);
- :func:`train_scene` - both, plus importing the result: the call a script makes;
- :func:`start_polling` - the UI path: a timer copies the job's state into
  ``scene.esgs.training`` and Blender's progress bar, and imports the result at the end.

Under ``blender -b`` and the bpy module timers never fire, so the operator uses the
blocking path there (see DESIGN.md).
"""
from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import bpy
import numpy as np

from ..core.apps import jobs
from ..core.errors import ConfigError, DatasetError
from ..core.apps.jobs import JobState, TrainingJob
from ..core.formats.scene_dir import PriorSource
from ..core.train.config import TrainConfig
from . import gaussians_import, preferences
from .properties import property_values
from .settings_training import chosen_method, method_settings

#: collection property naming the scene folder a collection was imported from
PROP_SCENE_DIR = "esgs_scene_dir"
#: what the COLMAP import stores: the model folder (SCENE/sparse/0) and the placement
PROP_COLMAP_SOURCE = "esgs_colmap_source"
PROP_COLMAP_TRANSFORM = "esgs_world_from_colmap"
#: object property: the run folder an imported result came from
PROP_RUN_DIR = "esgs_run_dir"

#: Tests replace the child command (``[python, -m, esgs.core.runtime.child]``) with a fake one.
TRAINER_OVERRIDE: Optional[Sequence[str]] = None
POLL_INTERVAL_S = 0.5


# --------------------------------------------------------------------------- scene folder


def scene_dir_of_collection(collection: bpy.types.Collection) -> Optional[Path]:
    """The scene folder a collection was imported from, or None."""
    if PROP_SCENE_DIR in collection:
        return Path(collection[PROP_SCENE_DIR])
    if PROP_COLMAP_SOURCE in collection:
        from ..core.formats.scene_dir import SceneDir

        model = Path(collection[PROP_COLMAP_SOURCE])
        # SCENE/sparse/0 -> SCENE, SCENE/sparse -> SCENE, SCENE/<model folder> -> SCENE
        above, beside = SceneDir(model.parent.parent), SceneDir(model.parent)
        if model.parent == above.sparse:
            return above.root
        return beside.root if model == beside.sparse or beside.images.is_dir() else model
    return None


def find_scene_dir(scene: bpy.types.Scene, explicit: str = "",
                   active_object: Optional[bpy.types.Object] = None) -> Path:
    """The scene folder to train on.

    ``explicit`` (the panel's folder field) wins; then the collection of the active object,
    then the first collection of the scene that a COLMAP import tagged.

    Raises:
        DatasetError: none found, or the folder does not exist.
    """
    candidates: list[Path] = []
    if explicit:
        candidates.append(Path(bpy.path.abspath(explicit)))
    else:
        collections = list(active_object.users_collection) if active_object is not None else []
        collections += [c for c in scene.collection.children_recursive if c not in collections]
        for collection in collections:
            folder = scene_dir_of_collection(collection)
            if folder is not None:
                candidates.append(folder)
                break
    if not candidates:
        raise DatasetError("no scene folder to train on",
                           hint="import a COLMAP scene (ESGS > Import COLMAP) or set the scene folder in the panel")
    folder = candidates[0]
    if not folder.is_dir():
        raise DatasetError("the scene folder does not exist", path=folder, hint="choose an existing scene folder")
    return folder


def use_for_training(scene: bpy.types.Scene, scene_dir: str | Path) -> None:
    """Make ``scene_dir`` the folder the Training section trains on and computes priors for
    (``scene.esgs.training.scene_dir``): what Render Dataset and Import COLMAP do with the
    folder they wrote or read, so the next step in the panel is Compute Priors or Train."""
    scene.esgs.training.scene_dir = str(Path(scene_dir))


def collection_of_scene_dir(scene: bpy.types.Scene, scene_dir: Path) -> Optional[bpy.types.Collection]:
    """The collection imported from ``scene_dir`` (for its placement), or None."""
    target = Path(scene_dir).resolve()
    for collection in scene.collection.children_recursive:
        folder = scene_dir_of_collection(collection)
        if folder is not None and folder.resolve() == target:
            return collection
    return None


# --------------------------------------------------------------------------- settings


def training_config(settings: Any) -> TrainConfig:
    """The TrainConfig of the panel's settings (``scene.esgs.training``).

    One loop over the dataclasses: the TrainConfig fields the panel holds, the chosen method
    (:func:`~.settings_training.chosen_method`: plain 3DGS unless ESGS, another method, an
    ESGS part or a prior source is chosen) and that method's settings from their properties.
    The child fills in every other setting's default and validates it (a ConfigError comes
    back as the job's error).

    Raises:
        ConfigError: the prior source is not one of :class:`~esgs.core.formats.scene_dir.PriorSource`.
    """
    values = property_values(settings, TrainConfig)
    method = chosen_method(settings)
    method_config = method_settings(settings, method)
    if getattr(method_config, "priors", ""):
        # a typo in a source set by a script would otherwise surface as a missing folder deep in the child
        PriorSource.parse(method_config.priors, tuple(PriorSource))
    elif getattr(method_config, "depth", False) or getattr(method_config, "normal", False):
        # said here in the panel's words (the trainer's message names its command-line flag)
        raise ConfigError("the depth and normal prior losses need prior maps",
                          hint="choose a Prior source in the Training section, or switch Depth and Normal off")
    values.update(method=method, method_config=method_config)
    return TrainConfig(**values)


def check_scene(scene_dir: str | Path, config: Optional[TrainConfig] = None,
                run_dir: str | Path | None = None) -> None:
    """Fail at once, in Blender, for what would make a new run fail in the child, before any
    run folder is made (the messages name the panel's controls).

    ``auto`` priors that are not there yet pass: the run computes them before its first step
    (:func:`esgs.core.methods.prepare_priors`; :func:`priors_made_first` says so).

    Raises:
        DatasetError: ``scene_dir`` is not a scene folder (no COLMAP model or no images/), or
            the prior source of ``config`` (other than auto) has no ``priors/<source>`` folder in it.
        ConfigError: ``run_dir`` already holds a run.
    """
    from ..core.colmap.io import find_model_dir
    from ..core.formats.run_dir import RunDir
    from ..core.formats.scene_dir import SceneDir
    from ..core.priors.io import available_prior_sources

    scene_dir = Path(scene_dir)
    where = "choose one as the Training section's Scene folder, or make one with Render Dataset or Import COLMAP"
    if not scene_dir.is_dir():
        raise DatasetError("the scene folder does not exist", path=scene_dir, hint=where)
    try:
        find_model_dir(scene_dir)
    except DatasetError as error:
        raise DatasetError(f"not a scene folder: {error.message}", path=scene_dir,
                           hint=f"a scene folder holds images/ and sparse/0; {where}") from None
    if not SceneDir(scene_dir).images.is_dir():
        raise DatasetError("not a scene folder: it has no images/ folder", path=scene_dir,
                           hint=f"a scene folder holds images/ and sparse/0; {where}")
    source = getattr(getattr(config, "method_config", None), "priors", "")
    if source and source != PriorSource.AUTO and source not in available_prior_sources(scene_dir):
        if source in (PriorSource.NDN, PriorSource.SFM):
            hint = f"press Compute Priors with {source} first, or choose another Prior source"
        elif source == PriorSource.LABELS:
            hint = "render them in the Labels section first, or choose another Prior source"
        else:
            hint = "choose another Prior source (gt priors come with a rendered synthetic scene)"
        raise DatasetError(f"the scene folder has no {source} priors", path=SceneDir(scene_dir).prior(source),
                           hint=hint)
    if run_dir is not None and RunDir(Path(run_dir)).exists():
        raise ConfigError("the run folder already holds a run", path=run_dir,
                          hint="press Resume Training to continue it, or choose another Run folder "
                               "(empty: a new one)")


def priors_made_first(scene_dir: str | Path, config: Optional[TrainConfig]) -> Optional[str]:
    """The prior source a new run of ``config`` computes before training (``"auto"`` when it
    trains with auto priors the scene folder does not hold yet), else None."""
    from ..core.formats.scene_dir import SceneDir

    settings = getattr(config, "method_config", None)
    source = getattr(settings, "priors", "")
    if source == PriorSource.AUTO and reads_prior_maps(settings) \
            and not SceneDir(Path(scene_dir)).has_prior_maps(source, "depth"):
        return str(source)
    return None


def reads_prior_maps(method_config: Any) -> bool:
    """Whether a method's settings switch on a part that reads prior maps (as
    :func:`esgs.core.methods.prepare_priors` decides: depth, normal or the sky loss)."""
    return any(getattr(method_config, name, False) for name in ("depth", "normal", "sky_loss_on"))


def new_run_dir(scene_dir: Path) -> Path:
    """A new, empty run folder name: ``<runs folder>/<scene name>-<date>-<time>``."""
    base = preferences.runs_folder(scene_dir) / f"{Path(scene_dir).name}-{time.strftime('%Y%m%d-%H%M%S')}"
    candidate, index = base, 1
    while candidate.exists():
        index += 1
        candidate = base.with_name(f"{base.name}-{index}")
    return candidate


# --------------------------------------------------------------------------- jobs


def job_key(scene_dir: str | Path) -> str:
    """One training job per scene folder."""
    return str(Path(scene_dir).resolve())


def start_training(scene_dir: str | Path, run_dir: str | Path | None = None, iterations: int = 30_000, *,
                   config: Optional[TrainConfig] = None, resume: bool = False, python: Optional[str] = None,
                   threads: Optional[int] = None, on_output: Optional[Callable[[str], None]] = None) -> TrainingJob:
    """Start the trainer for ``scene_dir`` in a child process and return its job (non-blocking).

    Args:
        scene_dir: the COLMAP scene folder.
        run_dir: the run folder (default: :func:`new_run_dir`); with ``resume`` an existing run.
        iterations: training steps.
        config: the training settings (e.g. :func:`training_config`); its scene, run folder and
            steps are this call's. None: the trainer's defaults (a resumed run keeps its own).
        python: interpreter (default: preferences, then :func:`esgs.core.apps.jobs.find_python`).
        threads: CPU threads for the child (default: the preference).

    Raises:
        ESGSError: a new run's scene folder, priors or run folder would fail it (:func:`check_scene`;
            nothing is written then), a job is already running for this scene folder, or the
            trainer cannot start.
    """
    scene_dir = Path(scene_dir)
    if not resume:
        check_scene(scene_dir, config, run_dir)
    run_dir = Path(run_dir) if run_dir else new_run_dir(scene_dir)
    threads = preferences.trainer_threads() if threads is None else threads
    trainer = list(TRAINER_OVERRIDE) if TRAINER_OVERRIDE else jobs.child_command(python or preferences.trainer_python())
    job = TrainingJob(scene_dir, run_dir, iterations=iterations, config=config, trainer=trainer, threads=threads or 0,
                      on_output=on_output)
    return jobs.start_job(job_key(scene_dir), job, resume=resume)


def wait_for_training(job: TrainingJob, *, report: Callable[[str], None] = print,
                      interval_s: float = 2.0) -> JobState:
    """Block until ``job`` ends, reporting its progress (one line every ``interval_s``; the
    last line names the held-out figures of a finished run, see :func:`status_line`)."""
    last = [0.0]

    def show(state: JobState) -> None:
        now = time.monotonic()
        if now - last[0] >= interval_s or not state.active:
            last[0] = now
            report(f"ESGS train: {status_line(state, job.run_dir)}")

    return job.wait(on_update=show, poll_s=min(0.5, interval_s))


#: the PSNR the trainer reports while it trains: a running mean over the views it just fitted
TRAINING_PSNR_LABEL = "training PSNR (last views)"
HELD_OUT_LABEL = "held-out"


def psnr_label(stage: str) -> str:
    """What the PSNR of a progress event of ``stage`` measures: the evaluation after training
    (stage ``eval``) renders the held-out views, training the views it is fitting."""
    return f"{HELD_OUT_LABEL} PSNR" if stage == "eval" else TRAINING_PSNR_LABEL


def status_line(state: JobState, run_dir: str | Path | None = None) -> str:
    """One line for a console or status bar, each PSNR under its own label.

    While the job runs: status, step, loss, the PSNR of the current stage (see
    :func:`psnr_label`), Gaussians, ETA. Once it ended with a run folder: the last training
    PSNR and the held-out PSNR / SSIM / LPIPS of ``metrics.json`` (:func:`run_results`),
    never the one under the other's name.
    """
    results = run_results(run_dir) if run_dir is not None and not state.active else None
    if results is not None:
        psnr_parts = format_results(results)
    elif state.psnr is not None and state.active:
        psnr_parts = [f"{psnr_label(state.stage)} {state.psnr:.2f} dB"]
    else:
        psnr_parts = []
    return state.summary(psnr_parts)


def run_results(run_dir: str | Path) -> Optional[dict[str, Any]]:
    """What a run measured, from its folder; None when it holds neither figure.

    Returns ``{"held_out": metrics.json's content or None, "training_psnr": the last PSNR the
    trainer reported while training (events.jsonl) or None, "comparison": the summary of the
    last Compare to Mesh of a Gaussian object imported from this run (or metrics.json's
    ``distances``), or None, "has_ground_truth_mesh": whether the run's scene folder has
    mesh/ground_truth.ply}``. ``held_out["split"]`` is ``"train"`` when the scene had no
    held-out views and the training views were evaluated instead.
    """
    import json

    from ..core.formats.run_dir import RunDir

    run = RunDir(Path(run_dir))
    held_out, training_psnr = _run_files(run)
    comparison = (held_out or {}).get("distances") if isinstance(held_out, dict) else None
    if comparison is None:
        comparison = run_comparison(run.root)
    if held_out is None and training_psnr is None and comparison is None:
        return None
    has_mesh = False
    try:
        config = json.loads(run.config.read_text())
        if config.get("scene"):
            from ..core.formats.scene_dir import SceneDir

            has_mesh = SceneDir(Path(config["scene"])).ground_truth_mesh.is_file()
    except (OSError, ValueError, AttributeError):
        pass
    return {"held_out": held_out if isinstance(held_out, dict) else None, "training_psnr": training_psnr,
            "comparison": comparison, "has_ground_truth_mesh": has_mesh}


_RUN_FILES_CACHE: dict[str, tuple[tuple, tuple[Optional[dict], Optional[float]]]] = {}


def _run_files(run: Any) -> tuple[Optional[dict], Optional[float]]:
    """(metrics.json's content, the last training PSNR of events.jsonl), cached on the files'
    sizes and times: the panel asks at every redraw and a long run's events file is large."""
    import json

    def stamp(path: Path) -> tuple:
        try:
            info = path.stat()
            return info.st_size, info.st_mtime_ns
        except OSError:
            return (None, None)

    key = (stamp(run.metrics), stamp(run.events))
    cached = _RUN_FILES_CACHE.get(str(run.root))
    if cached is not None and cached[0] == key:
        return cached[1]
    held_out = None
    try:
        held_out = json.loads(run.metrics.read_text())
    except (OSError, ValueError):
        pass
    training_psnr = None
    try:
        with open(run.events, encoding="utf-8", errors="replace") as handle:
            for line in handle:
                try:
                    event = json.loads(line)
                except ValueError:
                    continue
                metrics = event.get("metrics") if isinstance(event, dict) else None
                if isinstance(metrics, dict) and event.get("stage") == "train" \
                        and event.get("kind", "progress") == "progress" and metrics.get("psnr") is not None:
                    training_psnr = float(metrics["psnr"])
    except OSError:
        pass
    value = (held_out if isinstance(held_out, dict) else None, training_psnr)
    _RUN_FILES_CACHE[str(run.root)] = (key, value)
    return value


def run_comparison(run_dir: str | Path) -> Optional[dict[str, Any]]:
    """The last Compare to Mesh summary of a Gaussian object imported from ``run_dir``, or None."""
    from .compare_mesh import last_comparison

    target = str(Path(run_dir))
    for obj in getattr(bpy.data, "objects", ()):
        if obj.get(PROP_RUN_DIR) and str(Path(obj[PROP_RUN_DIR])) == target:
            summary = last_comparison(obj)
            if summary:
                return summary
    return None


def format_results(results: dict[str, Any]) -> list[str]:
    """Short labelled phrases of :func:`run_results`: training PSNR, held-out PSNR / SSIM /
    LPIPS (with the number of views), distances to the mesh."""
    parts = []
    if results.get("training_psnr") is not None:
        parts.append(f"{TRAINING_PSNR_LABEL} {results['training_psnr']:.2f} dB")
    held_out = results.get("held_out") or {}
    if held_out.get("psnr") is not None:
        label = HELD_OUT_LABEL if held_out.get("split", "test") == "test" else "training-view (no held-out split)"
        figures = [f"PSNR {held_out['psnr']:.2f} dB"]
        if held_out.get("ssim") is not None:
            figures.append(f"SSIM {held_out['ssim']:.3f}")
        if held_out.get("lpips") is not None:
            figures.append(f"LPIPS {held_out['lpips']:.3f}")
        views = held_out.get("views_count")
        parts.append(f"{label} {', '.join(figures)}" + (f" ({views} views)" if views else ""))
    comparison = results.get("comparison") or {}
    stats = comparison.get("gaussians_to_mesh_filtered") or comparison.get("gaussians_to_mesh") or {}
    if stats.get("mean") is not None:
        text = f"mean distance to mesh {stats['mean']:.3g} m"
        if comparison.get("fscore") is not None and comparison.get("threshold_m") is not None:
            text += f", F-score {comparison['fscore']:.3f} at {comparison['threshold_m']:.3g} m"
        parts.append(text)
    return parts


def import_run_result(run_dir: str | Path, scene: Optional[bpy.types.Scene] = None,
                      scene_dir: str | Path | None = None, **import_options: Any) -> bpy.types.Object:
    """Import ``RUN/point_cloud.ply``, placed like the COLMAP scene it was trained on."""
    from ..core.formats.run_dir import RunDir

    scene = scene or bpy.context.scene
    run_dir = Path(run_dir)
    collection = collection_of_scene_dir(scene, Path(scene_dir)) if scene_dir else None
    matrix = None
    if collection is not None and PROP_COLMAP_TRANSFORM in collection:
        # the trainer works in COLMAP's frame; the imported scene may have been re-oriented
        matrix = np.array([float(v) for v in collection[PROP_COLMAP_TRANSFORM]]).reshape(4, 4)
    obj = gaussians_import.import_gaussians(
        RunDir(run_dir).point_cloud, name=f"Gaussians {run_dir.name}", collection=collection or scene.collection,
        matrix_world=matrix, **import_options)
    obj[PROP_RUN_DIR] = str(run_dir)
    return obj


def train_scene(scene_dir: str | Path, run_dir: str | Path | None = None, iterations: int = 30_000, *,
                config: Optional[TrainConfig] = None, resume: bool = False, import_result: bool = True,
                python: Optional[str] = None, threads: Optional[int] = None,
                report: Callable[[str], None] = print, **import_options: Any) -> dict[str, Any]:
    """Train ``scene_dir`` blocking (console progress) and import the result.

    Returns ``{"state": JobState, "run_dir": Path, "object": Object | None}``. The object is
    None when training did not finish or ``import_result`` is False; check ``state.status``
    and ``state.error``.
    """
    job = start_training(scene_dir, run_dir, iterations, config=config, resume=resume, python=python,
                         threads=threads)
    state = wait_for_training(job, report=report)
    obj = None
    if state.status == jobs.FINISHED and import_result:
        obj = import_run_result(job.run_dir, scene_dir=scene_dir, **import_options)
    return {"state": state, "run_dir": job.run_dir, "object": obj}


# --------------------------------------------------------------------------- UI state


def copy_state(settings: Any, state: JobState) -> None:
    """Mirror a job state into ``scene.esgs.training`` (unknown numbers as -1)."""
    settings.status = state.status
    settings.stage = state.stage
    settings.step = state.step
    settings.total = state.total
    settings.progress = state.fraction
    settings.loss = state.loss if state.loss is not None else -1.0
    settings.psnr = state.psnr if state.psnr is not None else -1.0
    settings.n_gaussians = state.n_gaussians if state.n_gaussians is not None else -1
    settings.eta_s = state.eta_s if state.eta_s is not None else -1.0
    settings.error = state.error


def _redraw_views() -> None:
    window_manager = bpy.context.window_manager
    for window in getattr(window_manager, "windows", ()):
        for area in window.screen.areas:
            if area.type in ("VIEW_3D", "STATUSBAR"):
                area.tag_redraw()


def follow_job(scene_name: str, key: str, on_state: Callable[[Any, Any], None],
               on_end: Optional[Callable[[Any, Any, Any], None]] = None,
               owns: Optional[Callable[[Any, Any], bool]] = None) -> None:
    """Follow the background job of ``key`` with a timer (UI only): each poll passes the scene
    (or None once it is gone) and the job's state to ``on_state`` and moves the window
    manager's progress bar; when the job ends, ``on_end(scene, job, state)`` runs once.

    The timer follows the job ``key`` names now (the one just started), not a later one
    started under the same key before its next poll (Resume pressed within half a second
    of the end): that job has its own timer, and two would each import its result.

    The scene is the one the job was started from, found by its ``session_uid`` (renamed or
    not), or, in a file loaded since, the scene of that name for which ``owns(scene, job)``
    holds (the same file reopened); a scene of the same name in another file is not the
    job's: it gets neither the state nor the result."""
    def progress(call: str, *args: int) -> None:
        # the window manager of now: loading a file replaces it, and a removed one raises
        # (which would end the timer: no state, no import, no clean-up after a file load)
        window_manager = getattr(bpy.context, "window_manager", None)
        if window_manager is not None:
            getattr(window_manager, call)(*args)

    progress("progress_begin", 0, 1000)
    followed = jobs.get_job(key)
    started_from = bpy.data.scenes.get(scene_name)
    uid = started_from.session_uid if started_from is not None else None

    def find_scene() -> Any:
        for scene in bpy.data.scenes:
            if uid is not None and scene.session_uid == uid:
                return scene
        scene = bpy.data.scenes.get(scene_name)
        return scene if scene is not None and owns is not None and owns(scene, followed) else None

    def poll() -> Optional[float]:
        job = jobs.get_job(key)
        scene = find_scene()
        if job is None or followed is None:
            progress("progress_end")
            return None
        state = followed.state()
        if job is not followed and not state.active:
            # a new job of the key replaced this ended one: its own timer shows it (settings,
            # progress bar); this one only ends its own job
            if on_end is not None:
                on_end(scene, followed, state)
            return None
        if scene is not None:
            on_state(scene, state)
        progress("progress_update", int(state.fraction * 1000))
        _redraw_views()
        if state.active:
            return POLL_INTERVAL_S
        progress("progress_end")
        if on_end is not None:
            on_end(scene, followed, state)
        return None

    bpy.app.timers.register(poll, first_interval=POLL_INTERVAL_S, persistent=True)


def start_polling(scene_name: str, key: str, import_result: bool = True) -> None:
    """Follow the training job of ``key``: state into the scene's settings, the window
    manager's progress bar, and the result imported at the end (UI only)."""

    def import_at_end(scene: Any, job: Any, state: Any) -> None:
        if scene is None or state.status != jobs.FINISHED or not import_result:
            return
        # timers run without a window in the context; operators used by the import
        # (point-cloud conversion) want one
        windows = list(getattr(bpy.context.window_manager, "windows", ()))
        override = bpy.context.temp_override(window=windows[0]) if windows else contextlib.nullcontext()
        try:
            with override:
                import_run_result(job.run_dir, scene=scene, scene_dir=job.scene_dir)
        except Exception as error:  # noqa: BLE001 - a timer must not raise; show it instead
            scene.esgs.training.error = f"training finished but importing failed: {error}"

    follow_job(scene_name, key, lambda scene, state: copy_state(scene.esgs.training, state), import_at_end,
               owns=lambda scene, job: scene.esgs.training.last_run_dir == str(job.run_dir))
