"""How long a training run will take, said before it starts: the figure the Blender panel
shows below Iterations ("≈ 6 min (measured here)"), and for ESGS on ``auto`` priors that are
not made yet the one-time prior computation ("+ auto priors first, about 2 min").

The rule (plain Python, no torch, no bpy; every figure is a constant of this module)::

    seconds = STARTUP_S + iterations x step_s + held-out views x EVAL_VIEW_S

``step_s``, the seconds one training step takes, comes from (in this order):

1. **measured here**: the latest finished run this machine made (:func:`read_measured_run`
   reads its folder; :func:`latest_measured_run` picks it, a run of the same scene folder
   first): its steady seconds per step (the progress events' times over their steps, so the
   set-up before the first event and pauses between resumed sessions do not count), scaled
   to the new run by image pixels, by the methods' ratio in :data:`DEFAULT_STEP_S`, by a
   Gaussian cap below the count it reached, and by threads (:func:`thread_factor`).
2. **typical 2-core laptop**: :data:`DEFAULT_STEP_S` of the method, measured at 320x180 with
   about 40,000 Gaussians on 2 cores (README "Quick start": a 3DGS step 0.12 s, an ESGS step
   0.20 s; docs/benchmarks.md: Mip-Splatting and DropoutGS within 10 % of 3DGS at equal
   steps), scaled linearly by pixels (and by a Gaussian cap below 40,000; with another
   number of threads than 2, by :func:`thread_factor`, and the basis says so).

A step's cost is taken as linear in the image's pixels: the rasterizer's work is per pixel
and per Gaussian overlapping it. Evaluation after training renders each held-out view once
(0.2-0.3 s a view measured with SSIM and LPIPS at 320x180; :data:`EVAL_VIEW_S` rounds up).

:func:`estimate_priors_seconds` is the ``auto`` priors' one-time cost (docs/priors.md: on
10 views of 320x180 on 2 cores, stereo labels took 19-42 s, NDN 12-19 s, fusing ~1 s).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional

from ..formats.run_dir import RunDir

#: the image size the default figures were measured at
REFERENCE_WIDTH, REFERENCE_HEIGHT = 320, 180
REFERENCE_PIXELS = REFERENCE_WIDTH * REFERENCE_HEIGHT
#: the Gaussian count the default figures were measured at (the README's 40,000 cap)
REFERENCE_GAUSSIANS = 40_000
#: the threads the default figures were measured with
REFERENCE_THREADS = 2

#: seconds per training step at 320x180, 40,000 Gaussians, 2 cores, per method (README:
#: 3DGS 0.12 s, ESGS 0.20 s; docs/benchmarks.md's equal-step tables: Mip-Splatting 0.92x
#: and DropoutGS 0.97x the time of 3DGS, so they take its figure; the quick suite of
#: 2026-11-27, benchmarks/results/bench_quick_2026-11-27.json: PGSR 2.5x, its neighbour
#: renders and patch losses, and Scaffold-GS 1.1x the time of 3DGS as published)
DEFAULT_STEP_S = {"3dgs": 0.12, "esgs": 0.20, "mip-splatting": 0.12, "dropout-gs": 0.12, "pgsr": 0.30,
                  "scaffold-gs": 0.13}
#: a method not in :data:`DEFAULT_STEP_S` (a plug-in) is costed as plain 3DGS
FALLBACK_METHOD = "3dgs"

#: per run: starting the trainer process (importing torch), reading the scene, the steps
#: before the first progress event, writing the PLY (2-15 s measured on 2 cores)
STARTUP_S = 15.0
#: per held-out view: rendering it and scoring PSNR / SSIM / LPIPS (0.2-0.3 s measured)
EVAL_VIEW_S = 0.5

#: the share of a step that runs in parallel (Amdahl's law), fitted to 3DGS steps at 320x180:
#: 1 thread 0.17 s (docs/benchmarks.md, 346 steps in a minute), 2 threads 0.12 s, and 16
#: cores 0.074 s against ~0.12 s on 2 (docs/benchmarks.md, "The CUDA backend")
PARALLEL_SHARE = 0.55

#: ``auto`` priors, per view at 320x180 on 2 cores (docs/priors.md): stereo labels (scale
#: with pixels up to :data:`LABELS_MAX_WIDTH`, where the labels shrink the images), NDN
#: (a fixed working size: per view), SfM depth and fusing (about a second for 10 views)
LABELS_VIEW_S = 4.0
NDN_VIEW_S = 1.5
SFM_VIEW_S = 0.1
FUSE_VIEW_S = 0.1
#: per priors job: its process, torch, the NDN weights
PRIORS_STARTUP_S = 10.0
#: the width above which the stereo labels work on shrunk images (LabelsConfig.max_width)
LABELS_MAX_WIDTH = 960

#: what the estimate is based on (the panel shows it in brackets)
BASIS_MEASURED = "measured here"
BASIS_TYPICAL = "typical 2-core laptop"

#: a run whose progress events cover fewer steps than this says too little about a step's cost
MIN_MEASURED_STEPS = 20
#: run statuses whose step rate counts (train_result.json's ``status``)
FINISHED_STATUSES = ("completed", "time_limit")
#: at most this many of the newest run folders are read when looking for a measurement
MAX_RUNS_READ = 20


@dataclass(frozen=True)
class MeasuredRun:
    """What a finished run measured about this machine (:func:`read_measured_run`)."""

    run_dir: Path
    #: steady seconds per training step
    step_s: float
    #: the training steps the rate was measured over
    steps: int
    #: mean training image size (pixels, at the training resolution)
    width: float
    height: float
    method: str
    #: Gaussians at the end (None when not recorded)
    n_gaussians: Optional[int]
    #: the threads it trained with (0: the default, all cores)
    threads: int
    backend: str
    #: the scene folder it trained on ("" when not recorded)
    scene: str
    #: when it finished (train_result.json's modification time)
    finished_at: float

    @property
    def pixels(self) -> float:
        return self.width * self.height


def thread_factor(threads: Optional[int]) -> float:
    """A step's time with ``threads`` threads relative to one with :data:`REFERENCE_THREADS`
    (Amdahl's law with :data:`PARALLEL_SHARE`): 1 thread 1.38, 2 threads 1.0, 16 threads 0.67.
    ``threads`` None or 0 means all of this machine's cores."""
    count = _resolve_threads(threads)

    def time(n: int) -> float:
        return (1.0 - PARALLEL_SHARE) + PARALLEL_SHARE / n

    return time(count) / time(REFERENCE_THREADS)


def _resolve_threads(threads: Optional[int]) -> int:
    return int(threads) if threads and threads > 0 else max(1, os.cpu_count() or 1)


def _method_step_s(method: str) -> float:
    return DEFAULT_STEP_S.get(method, DEFAULT_STEP_S[FALLBACK_METHOD])


def _gaussian_factor(max_gaussians: Optional[int], reached: Optional[int]) -> float:
    """A cap below the count measured scales a step down in proportion (the cap bounds the
    count; nothing here predicts growth above what was measured)."""
    if not max_gaussians or not reached or max_gaussians >= reached:
        return 1.0
    return max_gaussians / reached


def _backends_clash(new: str, measured: str) -> bool:
    return {new, measured} == {"cpu", "cuda"}


def held_out_views(views: int, test_every: int) -> int:
    """How many of ``views`` the trainer holds out: index % test_every == 0 (3DGS's split)."""
    if test_every <= 0 or views <= 0:
        return 0
    return math.ceil(views / test_every)


def estimate_training_seconds(views: int, width: float, height: float, iterations: int, method: str,
                              threads: Optional[int] = None, measured: Optional[MeasuredRun] = None, *,
                              test_every: int = 8, max_gaussians: Optional[int] = None,
                              backend: str = "auto") -> tuple[float, str]:
    """``(seconds, basis)``: how long training ``iterations`` steps of ``method`` on ``views``
    images of ``width`` x ``height`` pixels (the training size) takes, evaluation included;
    ``basis`` is :data:`BASIS_MEASURED` or :data:`BASIS_TYPICAL` (or, for the default figures
    at another thread count, which one).

    Args:
        threads: the trainer's threads (None or 0: all cores). The default figures are for
            2 threads; None keeps them as they are (the basis is then a typical 2-core laptop).
        measured: this machine's latest usable run (:func:`latest_measured_run`); its rate is
            preferred unless its backend clashes with ``backend`` (cpu against cuda).
        test_every: the held-out split (every Nth view; 0: none).
        max_gaussians: the run's Gaussian cap (None: no cap).
    """
    pixels = max(float(width) * float(height), 1.0)
    if measured is not None and not _backends_clash(backend, measured.backend):
        step_s = (measured.step_s * pixels / max(measured.pixels, 1.0)
                  * _method_step_s(method) / _method_step_s(measured.method)
                  * _gaussian_factor(max_gaussians, measured.n_gaussians)
                  * thread_factor(threads) / thread_factor(measured.threads))
        basis = BASIS_MEASURED
    else:
        step_s = (_method_step_s(method) * pixels / REFERENCE_PIXELS
                  * _gaussian_factor(max_gaussians, REFERENCE_GAUSSIANS))
        basis = BASIS_TYPICAL
        if threads is not None and _resolve_threads(threads) != REFERENCE_THREADS:
            step_s *= thread_factor(threads)
            count = _resolve_threads(threads)
            basis = f"2-core figures scaled to {count} thread{'' if count == 1 else 's'}"
    seconds = STARTUP_S + max(int(iterations), 0) * step_s + held_out_views(views, test_every) * EVAL_VIEW_S
    return seconds, basis


def estimate_priors_seconds(views: int, width: float, height: float, *, labels: bool = True) -> float:
    """Seconds the ``auto`` priors of ``views`` images of ``width`` x ``height`` pixels (the
    scene's own size: priors are made at it) take to compute once: stereo labels (unless
    ``labels`` is False: a trainer without Blender's ``bpy`` module skips them), NDN, SfM
    depth and the fusion, at the 2-core figures."""
    per_view = NDN_VIEW_S + SFM_VIEW_S + FUSE_VIEW_S
    if labels:
        shrink = min(1.0, LABELS_MAX_WIDTH / max(float(width), 1.0))
        per_view += LABELS_VIEW_S * float(width) * float(height) * shrink * shrink / REFERENCE_PIXELS
    return PRIORS_STARTUP_S + max(int(views), 0) * per_view


def format_estimate(seconds: float) -> str:
    """``"6 min"``, ``"1 h 20 min"`` (to 10 minutes above 1.5 h): an estimate's precision;
    never below ``"1 min"``."""
    minutes = max(1, int(round(seconds / 60.0)))
    if minutes < 90:
        return f"{minutes} min"
    minutes = int(round(minutes / 10.0)) * 10
    hours, rest = divmod(minutes, 60)
    return f"{hours} h {rest} min" if rest else f"{hours} h"


# --------------------------------------------------------------------------- what a run measured


def _steady_step_s(events: Path) -> Optional[tuple[float, int]]:
    """``(seconds per step, steps)`` from the training progress events of ``events``: the
    time between consecutive events over the steps between them, summed; intervals more
    than five times slower than the median (a resume after a pause, a machine asleep) and
    those without new steps are left out. None when they cover under :data:`MIN_MEASURED_STEPS`."""
    points: list[tuple[int, float]] = []
    try:
        with open(events, encoding="utf-8", errors="replace") as handle:
            for line in handle:
                try:
                    event = json.loads(line)
                except ValueError:
                    continue
                if not isinstance(event, dict) or event.get("stage") != "train" \
                        or event.get("kind", "progress") != "progress":
                    continue
                step, when = event.get("step"), event.get("time")
                if isinstance(step, (int, float)) and isinstance(when, (int, float)):
                    points.append((int(step), float(when)))
    except OSError:
        return None
    intervals = [(b_step - a_step, b_time - a_time) for (a_step, a_time), (b_step, b_time) in zip(points, points[1:])
                 if b_step > a_step and b_time >= a_time]
    if not intervals:
        return None
    rates = sorted(seconds / steps for steps, seconds in intervals)
    median = rates[(len(rates) - 1) // 2]  # the lower one: two intervals, one a pause
    kept = [(steps, seconds) for steps, seconds in intervals if seconds / steps <= 5.0 * median]
    steps = sum(steps for steps, _ in kept)
    if steps < MIN_MEASURED_STEPS:
        return None
    return sum(seconds for _, seconds in kept) / steps, steps


def _training_image_size(run: RunDir, config: dict) -> Optional[tuple[int, float, float]]:
    """``(views, mean width, mean height)`` the run trained at: its cameras.json (the 3DGS
    layout, training resolution), else its scene's COLMAP cameras at its width/resolution."""
    try:
        cameras = json.loads(run.cameras_json.read_text())
        sizes = [(float(c["width"]), float(c["height"])) for c in cameras]
        if sizes:
            return len(sizes), sum(w for w, _ in sizes) / len(sizes), sum(h for _, h in sizes) / len(sizes)
    except (OSError, ValueError, TypeError, KeyError):
        pass
    scene = scene_image_size(config.get("scene") or "")
    if scene is None:
        return None
    views, width, height = scene
    return (views, *training_image_size(width, height, int(config.get("width") or 0),
                                        int(config.get("resolution") or 1)))


def read_measured_run(run_dir: str | os.PathLike) -> Optional[MeasuredRun]:
    """What the finished run in ``run_dir`` measured, or None when it is not a finished run
    (train_result.json's status ``completed`` or ``time_limit``), its progress events cover
    under :data:`MIN_MEASURED_STEPS` steps, or its image size cannot be told."""
    run = RunDir(Path(run_dir))
    try:
        result = json.loads(run.result.read_text())
        finished_at = run.result.stat().st_mtime
        config = json.loads(run.config.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(result, dict) or not isinstance(config, dict) or result.get("status") not in FINISHED_STATUSES:
        return None
    rate = _steady_step_s(run.events)
    size = _training_image_size(run, config)
    if rate is None or size is None:
        return None
    _, width, height = size
    n_gaussians = result.get("n_gaussians")
    return MeasuredRun(run_dir=run.root, step_s=rate[0], steps=rate[1], width=width, height=height,
                       method=str(config.get("method") or FALLBACK_METHOD),
                       n_gaussians=int(n_gaussians) if isinstance(n_gaussians, int) and n_gaussians > 0 else None,
                       threads=int(config.get("threads") or 0), backend=str(config.get("backend") or "auto"),
                       scene=str(config.get("scene") or ""), finished_at=finished_at)


def run_folders(folder: str | os.PathLike) -> list[Path]:
    """The run folders directly in ``folder`` (a runs folder: each holding train_result.json)."""
    try:
        return [entry for entry in Path(folder).iterdir() if RunDir(entry).result.is_file()]
    except OSError:
        return []


def latest_measured_run(run_dirs: Iterable[str | os.PathLike], scene_dir: str | os.PathLike | None = None,
                        ) -> Optional[MeasuredRun]:
    """The newest usable measurement among ``run_dirs`` (:func:`read_measured_run`; the
    :data:`MAX_RUNS_READ` newest finished runs are read): one of the scene folder
    ``scene_dir`` first (its Gaussian count says most about the next run), else any."""
    def finished(path: Path) -> float:
        try:
            return RunDir(path).result.stat().st_mtime
        except OSError:
            return -1.0

    unique = {str(Path(d)): Path(d) for d in run_dirs}
    newest = sorted((path for path in unique.values() if finished(path) >= 0), key=finished, reverse=True)
    runs = [run for run in (read_measured_run(path) for path in newest[:MAX_RUNS_READ]) if run is not None]
    if scene_dir is not None:
        target = _same_path(scene_dir)
        for run in runs:
            if run.scene and _same_path(run.scene) == target:
                return run
    return runs[0] if runs else None


def _same_path(path: str | os.PathLike) -> str:
    try:
        return str(Path(path).resolve())
    except (OSError, RuntimeError):
        return str(Path(path))


# --------------------------------------------------------------------------- the scene


def scene_image_size(scene_dir: str | os.PathLike) -> Optional[tuple[int, float, float]]:
    """``(views, mean width, mean height)`` of the registered images of the scene folder's
    COLMAP model (cameras and images files only, checked by the project's parsers), or None
    when there is no readable model."""
    from ..colmap import parse
    from ..colmap.io import find_model_dir
    from ..errors import ESGSError

    if not scene_dir:
        return None
    try:
        folder, extension = find_model_dir(scene_dir)
        if extension == "bin":
            cameras = parse.read_cameras_binary(folder / "cameras.bin")
            images = parse.read_images_binary(folder / "images.bin")
        else:
            cameras = parse.read_cameras_text(folder / "cameras.txt")
            images = parse.read_images_text(folder / "images.txt")
    except (ESGSError, OSError, ValueError):
        return None
    sizes = [(cameras[image.camera_id].width, cameras[image.camera_id].height)
             for image in images.values() if image.camera_id in cameras]
    if not sizes:
        return None
    return len(sizes), sum(w for w, _ in sizes) / len(sizes), sum(h for _, h in sizes) / len(sizes)


def training_image_size(width: float, height: float, target_width: int = 0, resolution: int = 1,
                        ) -> tuple[float, float]:
    """The size an image of ``width`` x ``height`` is trained at: ``target_width`` wide when
    above 0 (aspect kept), else divided by ``resolution`` (as the trainer's dataset does)."""
    scale = target_width / width if target_width > 0 and width > 0 else 1.0 / max(resolution, 1)
    return max(1.0, round(width * scale)), max(1.0, round(height * scale))
