"""The method comparison (``esgs bench``): 3DGS, Mip-Splatting, DropoutGS, ESGS ablations and
full ESGS on synthetic scenes, at equal step counts, written as ``OUT/benchmarks.md``.

Scenes are made with ``esgs scene`` in a child process (Blender's ``bpy`` never enters
this process) and cached under ``OUT/scenes/<preset>_s<seed>``. Each (scene, method,
seed) is one :class:`~.runs.RunTask` in ``OUT/runs/...``; tasks run through an
:class:`~.executor.Executor` (local process pool, or Ray with ``--address``), a failed run
is retried once, and a restart repeats only unfinished runs.
"""
from __future__ import annotations

import datetime
import platform
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from ..errors import ConfigError, ESGSError
from .ablate import MESH_PATH, available_priors
from .runs import RunTask
from .tables import COST_COLUMNS, QUALITY_COLUMNS, aggregate, markdown_table


@dataclass(frozen=True)
class BenchSuite:
    """Scenes (presets x seeds, rendered at ``resolution`` with ``views`` and ``samples``) and steps."""

    name: str
    presets: tuple[str, ...]
    seeds: tuple[int, ...]
    views: int
    resolution: str
    samples: int
    iterations: int
    points_per_view: int = 2000
    description: str = ""

    def scene_folder_name(self, preset: str, seed: int) -> str:
        """Cache key of a scene: everything that changes what ``esgs scene`` makes."""
        return f"{preset}_s{seed}_{self.views}v_{self.resolution}_{self.samples}spp_{self.points_per_view}p"


SUITES = {
    "quick": BenchSuite("quick", presets=("cratered_plain",), seeds=(0,), views=10, resolution="160x90", samples=8,
                        iterations=300, points_per_view=300, description="one small scene, one seed, 300 steps: ~8 minutes on 2 busy cores"),
    "full": BenchSuite("full", presets=("cratered_plain", "dune_field", "rocky_slope", "crater_survey_nadir"),
                       seeds=(0, 1, 2), views=30, resolution="480x270", samples=32, iterations=7000,
                       description="4 presets x 3 seeds at 480x270, 7,000 steps: hours on a CPU, best on a GPU cluster"),
}


@dataclass(frozen=True)
class Method:
    """A compared method: TrainConfig ``esgs``/``baselines`` values; ``priors``: needs prior maps."""

    key: str
    label: str
    esgs: tuple = ()
    baselines: tuple = ()
    priors: bool = False


def _method(key: str, label: str, *, esgs: Optional[dict] = None, baselines: Optional[dict] = None) -> Method:
    esgs = esgs or {}
    return Method(key, label, tuple(sorted(esgs.items())), tuple(sorted((baselines or {}).items())),
                  priors=bool(esgs.get("depth") or esgs.get("normal")))


METHODS = (
    _method("3dgs", "3DGS"),
    _method("mip_splatting", "Mip-Splatting", baselines={"mip_splatting": True}),
    _method("dropout_gs", "DropoutGS", baselines={"dropout_gs": True, "dropout_rate": 0.1}),
    _method("esgs_depth", "ESGS: depth prior", esgs={"depth": True}),
    _method("esgs_normal", "ESGS: normal prior", esgs={"normal": True}),
    _method("esgs_depth_normal", "ESGS: depth + normal", esgs={"depth": True, "normal": True}),
    _method("esgs_full", "ESGS (depth + normal + GPDFN)", esgs={"depth": True, "normal": True, "gpdfn": True,
                                                                 "fused_k": 3}),
)


def make_scene(preset: str, seed: int, suite: BenchSuite, scenes_dir: Path) -> Path:
    """``esgs scene`` into ``scenes_dir/<preset>_s<seed>`` unless it is there (the folder appears complete)."""
    folder = Path(scenes_dir) / suite.scene_folder_name(preset, seed)
    if (folder / "sparse").is_dir():
        return folder
    command = [sys.executable, "-m", "esgs.core.cli", "scene", "--preset", preset, "--seed", str(seed),
               "--views", str(suite.views), "--resolution", suite.resolution, "--samples", str(suite.samples),
               "--points-per-view", str(suite.points_per_view), "--out", str(folder)]
    completed = subprocess.run(command, capture_output=True, text=True)
    if completed.returncode != 0:
        raise ESGSError(f"esgs scene failed for {preset} seed {seed}: {completed.stdout[-500:]}{completed.stderr[-1500:]}",
                        path=folder, hint="run the command by hand: " + " ".join(command[1:]))
    return folder


def plan_bench(scenes: dict[str, tuple[Path, int]], out: Path, *, iterations: int, methods: Sequence[Method] = METHODS,
               train: Optional[dict] = None) -> tuple[list[RunTask], list[str]]:
    """Run tasks for every scene (name -> (folder, seed)) and method, and notes on what was left out."""
    tasks, notes = [], []
    for scene_name, (folder, seed) in scenes.items():
        found = available_priors(folder)
        source = next((s for s in ("gt", "labels", "ndn", "sfm") if s in found), "")
        mesh = folder / MESH_PATH
        for method in methods:
            esgs = dict(method.esgs)
            if method.priors:
                needed = {kind for kind in ("depth", "normal") if esgs.get(kind)}
                if not source or not needed <= found.get(source, set()):
                    notes.append(f"{method.label} skipped on {scene_name}: no {'/'.join(sorted(needed))} priors")
                    continue
                esgs["priors"] = source
            config = {**(train or {}), "iterations": iterations, "seed": seed, "esgs": esgs,
                      "baselines": dict(method.baselines)}
            tasks.append(RunTask(name=f"{scene_name}/{method.key}", scene=folder,
                                 out=Path(out) / "runs" / scene_name / method.key, config=config, variant=method.label,
                                 seed=seed, scene_name=scene_name, mesh=mesh if mesh.is_file() else None))
    return tasks, notes


def machine_description() -> dict[str, Any]:
    """Where the figures come from: OS, CPU, cores, Python, torch and the GPU if any."""
    import os

    import torch

    info = {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__,
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}
    return info


def bench_markdown(report: dict) -> str:
    """docs-style Markdown of a bench report (see :func:`run_bench`)."""
    suite = report["suite"]
    machine = report["machine"]
    lines = [f"# Benchmarks: {suite['name']} suite", "",
             f"Date (UTC): {report['date']}. Machine: {machine['platform']}, {machine['processor']}, "
             f"{machine['cpu_count']} logical CPUs, Python {machine['python']}, torch {machine['torch']}, "
             f"GPU: {machine['gpu'] or 'none'}. Executor: {report['executor']}.", "",
             f"Scenes: `esgs scene` presets {', '.join(suite['presets'])} x seeds "
             f"{', '.join(map(str, suite['seeds']))} ({suite['views']} views, {suite['resolution']}, "
             f"{suite['samples']} samples, {suite['points_per_view']} SfM points per view); every method "
             f"trains {report['iterations']} steps with the same seed as its scene. Quality on the held-out "
             "views (every 8th image); distances from the Gaussian centres with opacity >= 0.5 to "
             "mesh/ground_truth.ply (scene units, metres). Train time is training only; peak RSS is the run's process (ru_maxrss); render time is one held-out "
             "frame, mean over the held-out views. Mean ± std over scenes and seeds.", "",
             f"Command: `{report['command']}`", "", "## All scenes", "",
             markdown_table(report["overall"], QUALITY_COLUMNS), "",
             markdown_table(report["overall"], COST_COLUMNS)]
    for scene_name, rows in report["per_scene"].items():
        lines += [f"## {scene_name}", "", markdown_table(rows, QUALITY_COLUMNS + COST_COLUMNS)]
    if report["notes"] or report["failed"]:
        lines += ["## Notes", ""]
        lines += [f"- {note}" for note in report["notes"]]
        lines += [f"- FAILED {item['run']} after {item['attempts']} attempts: {item['error'].splitlines()[0]}"
                  for item in report["failed"]]
        lines.append("")
    return "\n".join(lines)


def run_bench(out: str | Path, suite: str | BenchSuite = "quick", *, executor: Any = None,
              scenes: Optional[dict[str, tuple[Path, int]]] = None, methods: Sequence[Method] = METHODS,
              iterations: Optional[int] = None, train: Optional[dict] = None, command: str = "",
              on_outcome: Optional[Callable[[Any], None]] = None) -> dict:
    """Make (or reuse) the suite's scenes, run every method on each, write benchmarks.md/.json.

    ``scenes`` (name -> (folder, seed)) replaces the suite's generated scenes (tests,
    existing folders). ``executor``: an :class:`~.executor.Executor` (default: a local
    pool of one worker). Returns the report dict (also ``OUT/benchmarks.json``).
    """
    from ..io_utils import atomic_write_json, atomic_write_text
    from .executor import LocalExecutor, run_tasks
    from .runs import run_task

    out = Path(out)
    if isinstance(suite, str):
        if suite not in SUITES:
            raise ConfigError(f"unknown suite {suite!r}", hint=f"use one of {', '.join(SUITES)}")
        suite = SUITES[suite]
    iterations = iterations or suite.iterations
    if scenes is None:
        scenes = {f"{preset}_s{seed}": (make_scene(preset, seed, suite, out / "scenes"), seed)
                  for preset in suite.presets for seed in suite.seeds}
    tasks, notes = plan_bench(scenes, out, iterations=iterations, methods=methods, train=train)
    own_executor = executor is None
    executor = executor or LocalExecutor(1)
    try:
        outcomes = run_tasks(tasks, run_task, executor, retries=1, on_outcome=on_outcome)
    finally:
        if own_executor:
            executor.close()
    summaries = [outcome.result for outcome in outcomes if outcome.status in ("done", "skipped")]
    failed = [{"run": outcome.task.name, "error": outcome.error or "", "attempts": outcome.attempts}
              for outcome in outcomes if outcome.status == "failed"]
    keys = [key for key, _, _ in QUALITY_COLUMNS + COST_COLUMNS]
    per_scene: dict[str, list[dict]] = {}
    for scene_name in scenes:
        per_scene[scene_name] = aggregate([s for s in summaries if s["scene"] == scene_name], keys)
    report = {
        "suite": {"name": suite.name, "presets": list(suite.presets), "seeds": list(suite.seeds), "views": suite.views,
                  "resolution": suite.resolution, "samples": suite.samples, "points_per_view": suite.points_per_view,
                  "iterations": suite.iterations},
        "iterations": iterations, "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M"),
        "machine": machine_description(), "executor": type(executor).__name__, "command": command or "run_bench(...)",
        "overall": aggregate(summaries, keys), "per_scene": per_scene, "runs": summaries, "notes": notes,
        "failed": failed,
    }
    atomic_write_json(out / "benchmarks.json", report)
    atomic_write_text(out / "benchmarks.md", bench_markdown(report))
    return report
