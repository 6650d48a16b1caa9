"""The Training section's time estimate, shown below Iterations: the engine's rule
(:mod:`esgs.core.apps.estimate`) fed with the panel's settings, the scene folder's images
and the runs this machine finished.

The panel asks at every redraw, so what needs files (the scene's COLMAP cameras, the run
folders, whether the ``auto`` priors exist) is read once per scene folder, runs folder and
job states, and again at most every :data:`REFRESH_S` seconds (a memo here); the arithmetic
on the settings (iterations, width, method ...) is redone at each draw, which costs nothing.

Runs "this machine finished" are those the add-on knows: the last run of every scene of the
.blend (``scene.esgs.training.last_run_dir``) and the run folders beside them and in the
runs folder of the training scene (:func:`.preferences.runs_folder`).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import bpy

from ..core.apps import estimate
from ..core.formats.scene_dir import PriorSource, SceneDir
from . import preferences, settings_training, training_job

#: how long what was read from files is trusted (a run finished by another program, priors
#: computed on the command line)
REFRESH_S = 30.0


@dataclass(frozen=True)
class _Facts:
    """What the estimate needs from files."""

    #: (views, mean width, mean height) of the scene folder's images, or None
    scene: Optional[tuple[int, float, float]]
    measured: Optional[estimate.MeasuredRun]
    auto_priors_present: bool


_MEMO: dict[tuple, tuple[float, _Facts]] = {}


def clear_cache() -> None:
    """Forget what was read (tests; the memo otherwise refreshes itself)."""
    _MEMO.clear()


def _known_run_dirs(scene_dir: Path) -> tuple[list[str], str]:
    """(the last run folder of every scene of the .blend, the runs folder new runs go to)."""
    last = []
    for scene in getattr(bpy.data, "scenes", ()):
        settings = getattr(getattr(scene, "esgs", None), "training", None)
        if settings is not None and settings.last_run_dir:
            last.append(bpy.path.abspath(settings.last_run_dir))
    try:
        runs = str(preferences.runs_folder(scene_dir))
    except (AttributeError, RuntimeError, OSError):
        runs = ""
    return last, runs


def _read_facts(scene_dir: Path, last_runs: list[str], runs_folder: str) -> _Facts:
    candidates: list[Path] = [Path(path) for path in last_runs]
    for folder in {runs_folder, *(str(Path(path).parent) for path in last_runs)}:
        if folder:
            candidates += estimate.run_folders(folder)
    return _Facts(scene=estimate.scene_image_size(scene_dir),
                  measured=estimate.latest_measured_run(candidates, scene_dir),
                  auto_priors_present=SceneDir(scene_dir).has_prior_maps(PriorSource.AUTO.value, "depth"))


def _facts(scene_dir: Path, context: Any) -> _Facts:
    last_runs, runs_folder = _known_run_dirs(scene_dir)
    scene = context.scene.esgs
    # a finished job (training or priors) changes what the files say: its state is in the key
    key = (str(scene_dir), runs_folder, tuple(last_runs), scene.training.status, scene.priors.status)
    now = time.monotonic()
    cached = _MEMO.get(key)
    if cached is not None and now - cached[0] < REFRESH_S:
        return cached[1]
    facts = _read_facts(scene_dir, last_runs, runs_folder)
    if len(_MEMO) > 16:
        _MEMO.clear()
    _MEMO[key] = (now, facts)
    return facts


def estimate_lines(settings: Any, context: Any, scene_dir: Optional[Path]) -> list[str]:
    """The label lines to show below Iterations, e.g. ``["≈ 6 min (measured here)"]``, plus
    ``"+ auto priors first, about 2 min"`` for an ESGS run that computes its auto priors
    first; none while there is no readable scene folder."""
    if scene_dir is None:
        return []
    facts = _facts(Path(scene_dir), context)
    if facts.scene is None:
        return []
    views, native_width, native_height = facts.scene
    width, height = estimate.training_image_size(native_width, native_height, int(settings.width))
    method = settings_training.chosen_method(settings)
    threads = preferences.trainer_threads(context) or os.cpu_count()
    seconds, basis = estimate.estimate_training_seconds(
        views, width, height, int(settings.iterations), method, threads=threads, measured=facts.measured,
        test_every=int(settings.test_every), max_gaussians=int(settings.max_gaussians), backend=settings.backend)
    lines = [f"≈ {estimate.format_estimate(seconds)} ({basis})"]
    method_config = settings_training.method_settings(settings, method)
    if method == settings_training.ESGS_METHOD and getattr(method_config, "priors", "") == PriorSource.AUTO.value \
            and training_job.reads_prior_maps(method_config) and not facts.auto_priors_present:
        priors_s = estimate.estimate_priors_seconds(views, native_width, native_height)
        lines.append(f"+ auto priors first, about {estimate.format_estimate(priors_s)}")
    return lines
