"""The method comparison (``esgs bench``): 3DGS, Mip-Splatting, DropoutGS, ESGS ablations and
full ESGS on synthetic scenes, at equal step counts and at equal wall-clock budgets, written
as ``OUT/benchmarks.md``.

Scenes are made with ``esgs scene`` in a child process (Blender's ``bpy`` never enters
this process) and cached under ``OUT/scenes/<preset>_s<seed>_...``. Each (scene, method,
seed) is one :class:`~.runs.RunTask` in ``OUT/runs/...`` (equal steps) and, with a budget,
one more in ``OUT/runs_budget/...`` (equal training time: ``max_minutes`` with a step cap);
tasks run through an :class:`~.executor.Executor` (local process pool, or Ray), a failed run
is retried once, and a restart repeats only unfinished runs and runs whose saved settings
differ from the ones the bench asks for now (a changed default, another prior source).

The prior-based rows use the priors a user would have: NDN's by default (``priors="ndn"``,
computed once per scene with ``esgs priors --method ndn`` and kept in the scene), or SfM's.
One extra row, full ESGS with the generator's exact depth and normals, is labelled as the
upper bound: no real scene has those priors.
"""
from __future__ import annotations

import datetime
import platform
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from ..errors import ConfigError, ESGSError
from ..runtime import run_job
from ..train.config import VANILLA_3DGS
from ..formats.scene_dir import PriorSource, SceneDir, names
from .ablate import available_priors
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
    budget_minutes: float = 0.0
    budget_step_cap: int = 0
    description: str = ""

    @property
    def step_cap(self) -> int:
        """Step cap of the budget runs (0 in the suite = twice the equal-step count)."""
        return self.budget_step_cap or 2 * self.iterations

    def scene_folder_name(self, preset: str, seed: int) -> str:
        """Cache key of a scene: everything that changes what ``esgs scene`` makes."""
        return f"{preset}_s{seed}_{self.views}v_{self.resolution}_{self.samples}spp_{self.points_per_view}p"


SUITES = {
    # minutes on this 2-core machine: one small scene, one seed
    "quick": BenchSuite("quick", presets=("cratered_plain",), seeds=(0,), views=10, resolution="160x90", samples=8,
                        iterations=300, points_per_view=300, budget_minutes=0.5,
                        description="cratered_plain seed 0, 10 views 160x90, 300 steps, and 0.5 min budgets: "
                                    "15-30 minutes on 2 busy cores"),
    # the comparison of the issue, sized for a 2-core CPU machine (see docs/benchmarks.md)
    "full": BenchSuite("full", presets=("cratered_plain", "dune_field"), seeds=(0, 1, 2), views=12,
                       resolution="320x180", samples=16, iterations=500, points_per_view=1000, budget_minutes=1.0,
                       description="cratered_plain, dune_field x seeds 0 1 2, 12 views 320x180, 500 steps, and "
                                   "1 min budgets: ~1.5 hours on 2 idle cores (two Ray workers)"),
    # for bigger machines only (a GPU, or a Ray cluster): days on a 2-core CPU
    "large": BenchSuite("large", presets=("cratered_plain", "dune_field", "rocky_slope", "crater_survey_nadir"),
                        seeds=(0, 1, 2), views=30, resolution="480x270", samples=32, iterations=7000,
                        budget_minutes=20.0, budget_step_cap=30_000,
                        description="4 presets x 3 seeds, 30 views 480x270, 7,000 steps, and 20 min budgets: "
                                    "for a GPU machine or a Ray cluster"),
}


@dataclass(frozen=True)
class Method:
    """A compared row: ``method`` (a registered training method) with ``settings`` (fields of
    its settings dataclass; ``full``: start from :func:`esgs.core.methods.full_esgs` for the
    row's prior source); ``priors``: needs prior maps; ``prior_source``: a fixed
    ``priors/<source>`` ("" = the bench's choice, see :func:`plan_bench`); ``train``: TrainConfig
    fields set on the row (the published baselines run :data:`~esgs.core.train.config.VANILLA_3DGS`)."""

    key: str
    label: str
    method: str = "3dgs"
    settings: tuple = ()
    full: bool = False
    priors: bool = False
    prior_source: str = ""
    train: tuple = ()

    def method_config(self, source: str, scene: Path) -> Optional[dict]:
        """The row's ``method_config`` on ``scene`` with prior source ``source``."""
        from ..config import config_to_dict
        from ..methods import full_esgs

        if self.full:
            return config_to_dict(full_esgs(source, scene=scene, **dict(self.settings)))
        settings = dict(self.settings)
        if self.priors:
            settings["priors"] = source
        return settings or None


def _method(key: str, label: str, method: str = "3dgs", *, settings: Optional[dict] = None, full: bool = False,
            prior_source: str = "", vanilla: bool = False) -> Method:
    settings = settings or {}
    return Method(key, label, method, tuple(sorted(settings.items())), full,
                  priors=full or bool(settings.get("depth") or settings.get("normal")), prior_source=prior_source,
                  train=tuple(sorted(VANILLA_3DGS.items())) if vanilla else ())


#: Where the prior-based rows may take their priors from (``--priors``).
PRIOR_SOURCES = names(PriorSource.for_synthetic_scenes())
#: The sources ``esgs priors`` can compute for a scene that lacks them.
COMPUTED_PRIOR_SOURCES = names(PriorSource.computed())
#: ... and those :func:`ensure_priors` can (``labels``: ``esgs labels --reconstruct``, needs bpy).
ENSURED_PRIOR_SOURCES = (*COMPUTED_PRIOR_SOURCES, *names(tuple(s for s in PriorSource if s.made_by_labels)))
UPPER_BOUND_KEY = "esgs_full_gt"


#: The published baselines run as published (``vanilla``: constant background, no sky masks);
#: "3DGS + sky model" is plain 3DGS with this tool's defaults, so the table separates what the
#: sky model adds from what ESGS's priors add (every ESGS row uses the defaults).
METHODS = (
    _method("3dgs", "3DGS", vanilla=True),
    _method("3dgs_sky", "3DGS + sky model (our defaults)"),
    _method("mip_splatting", "Mip-Splatting", "mip-splatting", vanilla=True),
    _method("dropout_gs", "DropoutGS", "dropout-gs", settings={"dropout_rate": 0.1}, vanilla=True),
    _method("esgs_depth", "ESGS: depth prior", "esgs", settings={"depth": True}),
    _method("esgs_normal", "ESGS: normal prior", "esgs", settings={"normal": True}),
    _method("esgs_depth_normal", "ESGS: depth + normal", "esgs", settings={"depth": True, "normal": True}),
    _method("esgs_full", "ESGS (depth + normal + GPDFN)", "esgs", full=True),
    # not a method a user can run on real data: the same ESGS fed the exact synthetic depth and normals
    _method(UPPER_BOUND_KEY, "ESGS, ground-truth priors (upper bound)", "esgs", full=True, prior_source="gt"),
)


def ensure_priors(scene: Path, source: str) -> Path:
    """``SCENE/priors/<source>``, computed in a child process when the scene has none:
    ``esgs priors --method <source>`` (ndn, sfm) or ``esgs labels --reconstruct`` (labels: a
    mesh rebuilt from the images and poses, never the true mesh); ``gt`` priors come only
    from the generator.

    Both commands write the folder atomically, so an interrupted bench leaves either the
    whole folder or none, and a restart reuses it.
    """
    scene = Path(scene)
    folder = SceneDir(scene).prior(source)
    if source in available_priors(scene):
        return folder
    if source not in ENSURED_PRIOR_SOURCES:
        raise ConfigError(f"the scene has no {source} priors and the bench cannot compute them", path=scene,
                          hint=f"use --priors {' or '.join(COMPUTED_PRIOR_SOURCES)}, or a scene made by esgs scene")
    if source == "labels":
        from ..labels.pipeline import LabelJob

        job, config, what, options = "labels", LabelJob(scene=scene, reconstruct=True), "esgs labels", "--reconstruct"
    else:
        # the PriorsSettings fields as a dict: the child builds the dataclass
        job, config, what, options = "priors", {"scene": str(scene), "method": source}, "esgs priors", f"--method {source}"
    try:
        run_job(job, config, task=f"{what} {options}")
    except ESGSError as error:
        raise type(error)(f"{what} {options} failed: {error.message}", path=error.path or scene,
                          hint=error.hint or f"run the command by hand: {what} {scene} {options}") from error
    return folder


def make_scene(preset: str, seed: int, suite: BenchSuite, scenes_dir: Path) -> Path:
    """``esgs scene`` into ``scenes_dir/<preset>_s<seed>`` unless it is there (the folder appears complete)."""
    from ..terrain.scene_job import SceneJob, parse_resolution, render_scene

    folder = Path(scenes_dir) / suite.scene_folder_name(preset, seed)
    if SceneDir(folder).has_model():
        return folder
    width, height = parse_resolution(suite.resolution)
    job = SceneJob(preset=preset, seed=seed, views=suite.views, width=width, height=height, samples=suite.samples,
                   points_per_view=suite.points_per_view)
    try:
        render_scene(job, folder)
    except ESGSError as error:
        raise type(error)(f"esgs scene failed for {preset} seed {seed}: {error.message}", path=error.path or folder,
                          hint=error.hint) from error
    return folder


def plan_bench(scenes: dict[str, tuple[Path, int]], out: Path, *, iterations: int, methods: Sequence[Method] = METHODS,
               train: Optional[dict] = None, budget_minutes: float = 0.0, budget_step_cap: int = 0,
               priors: str = "ndn") -> tuple[list[RunTask], list[str]]:
    """Run tasks for every scene (name -> (folder, seed)) and method, and notes on what was left out.

    Prior-based methods read ``priors/<priors>`` (a method's own ``prior_source`` wins, e.g.
    the gt upper bound); a scene without the maps a method needs skips it with a note.

    Equal-step tasks train ``iterations`` steps in ``OUT/runs/<scene>/<method>``. With
    ``budget_minutes`` > 0 every method also trains in ``OUT/runs_budget/<scene>/<method>``
    for that much training time (``max_minutes``), up to ``budget_step_cap`` steps (0 =
    twice ``iterations``); its learning-rate and densification schedules are those of the cap.
    """
    tasks, notes = [], []
    modes = [("steps", "runs", {"iterations": iterations})]
    if budget_minutes > 0:
        modes.append(("budget", "runs_budget", {"iterations": budget_step_cap or 2 * iterations,
                                                "max_minutes": float(budget_minutes)}))
    if priors not in PRIOR_SOURCES:
        raise ConfigError(f"unknown prior source {priors!r}", hint=f"use one of {', '.join(PRIOR_SOURCES)}")
    for scene_name, (folder, seed) in scenes.items():
        found = available_priors(folder)
        mesh = SceneDir(folder).ground_truth_mesh
        for method in methods:
            source = method.prior_source or priors
            method_config = method.method_config(source, folder)
            if method.priors:
                needed = {kind for kind in ("depth", "normal") if (method_config or {}).get(kind)}
                if not needed <= found.get(source, set()):
                    notes.append(f"{method.label} skipped on {scene_name}: no {source} "
                                 f"{'/'.join(sorted(needed))} priors")
                    continue
            for mode, folder_name, schedule in modes:
                config = {**(train or {}), **dict(method.train), **schedule, "seed": seed,
                          "method": method.method, "method_config": method_config}
                suffix = "" if mode == "steps" else "@budget"
                tasks.append(RunTask(name=f"{scene_name}/{method.key}{suffix}", scene=folder,
                                     out=Path(out) / folder_name / scene_name / method.key, config=config,
                                     variant=method.label, seed=seed, scene_name=scene_name,
                                     mesh=mesh if mesh.is_file() else None))
    return tasks, notes


def machine_description() -> dict[str, Any]:
    """Where the figures come from: OS, CPU, cores, Python, torch and the GPU if any."""
    import os

    import torch

    info = {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__,
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}
    return info


#: The budget tables also show how far each method got.
STEPS_COLUMN = (("steps", "steps reached", 0),)


def _comparison_markdown(part: dict, title: str) -> list[str]:
    """The tables of one comparison (equal steps or equal budget): all scenes, then each scene."""
    extra = STEPS_COLUMN if part.get("budget_minutes") else ()
    lines = [f"## {title}: all scenes", "", markdown_table(part["overall"], QUALITY_COLUMNS), "",
             markdown_table(part["overall"], extra + COST_COLUMNS)]
    for scene_name, rows in part["per_scene"].items():
        lines += [f"### {title}: {scene_name}", "", markdown_table(rows, QUALITY_COLUMNS + extra + COST_COLUMNS)]
    return lines


def _priors_sentence(priors: Optional[dict]) -> str:
    priors = priors or {}
    source = priors.get("source", "gt")
    made_by = {"ndn": "NDN's relative depth and normals (`esgs priors --method ndn`, weights "
                      f"{', '.join(priors.get('weights') or ['shipped'])}), pinned to each view's SfM points",
               "sfm": "the sparse SfM depth (`esgs priors --method sfm`)",
               "gt": "the generator's exact depth and normals"}[source]
    sentence = f"Priors: the ESGS rows use {made_by}."
    if source != "gt":
        sentence += (" The row 'ESGS, ground-truth priors (upper bound)' is the same full ESGS fed the generator's "
                     "exact depth and normals: a bound on what a perfect prior would give, not a method a user can "
                     "run on real data.")
    return sentence


def bench_markdown(report: dict) -> str:
    """docs-style Markdown of a bench report (see :func:`run_bench`)."""
    suite = report["suite"]
    machine = report["machine"]
    budget = report.get("budget")
    lines = [f"# Benchmarks: {suite['name']} suite", "",
             f"Date (UTC): {report['date']}. Machine: {machine['platform']}, {machine['processor']}, "
             f"{machine['cpu_count']} logical CPUs, Python {machine['python']}, torch {machine['torch']}, "
             f"GPU: {machine['gpu'] or 'none'}. Executor: {report['executor']}.", "",
             f"Scenes: `esgs scene` presets {', '.join(suite['presets'])} x seeds "
             f"{', '.join(map(str, suite['seeds']))} ({suite['views']} views, {suite['resolution']}, "
             f"{suite['samples']} samples, {suite['points_per_view']} SfM points per view); every method "
             f"trains with the same seed as its scene, {report['iterations']} steps for the equal-step comparison"
             + (f" and {budget['budget_minutes']:g} minutes of training (at most {budget['step_cap']} steps, the "
                "schedule of that cap) for the equal-budget one" if budget else "")
             + ". Quality on the held-out "
             "views (every 8th image); distances from the Gaussian centres with opacity >= 0.5 to "
             "mesh/ground_truth.ply (scene units, metres). Train time is training only; peak RSS is the run's "
             "process (ru_maxrss); render time is one held-out frame, mean over the held-out views. "
             "Mean ± std over scenes and seeds.", "",
             _priors_sentence(report.get("priors")), "",
             f"Command: `{report['command']}`", ""]
    lines += _comparison_markdown(report, f"At equal step count ({report['iterations']} steps)")
    if budget:
        lines += ["", *_comparison_markdown(budget, f"At equal wall-clock budget ({budget['budget_minutes']:g} min)")]
    if report["notes"] or report["failed"]:
        lines += ["## Notes", ""]
        lines += [f"- {note}" for note in report["notes"]]
        lines += [f"- FAILED {item['run']} after {item['attempts']} attempts: {item['error'].splitlines()[0]}"
                  for item in report["failed"]]
        lines.append("")
    return "\n".join(lines)


def _prior_description(source: str, scenes: dict[str, tuple[Path, int]]) -> dict[str, Any]:
    """The prior source of the bench and, for NDN, the weights its maps were computed with
    (the ``weights`` header of each scene's first depth map)."""
    from ..formats.imageio import read_exr

    weights = set()
    if source == "ndn":
        for folder, _ in scenes.values():
            for path in sorted(SceneDir(folder).prior_maps(source, "depth").glob("*.exr"))[:1]:
                try:
                    weights.add(Path(read_exr(path)[1].get("weights", "")).name)
                except (OSError, ValueError, ESGSError):
                    pass  # the description is informative only; the run itself checks the maps
    return {"source": source, "weights": sorted(w for w in weights if w)}


def _comparison(summaries: list[dict], scene_names: Sequence[str], keys: Sequence[str]) -> dict:
    """Rows over all scenes and per scene (mean ± std over seeds) of one set of run summaries."""
    return {"overall": aggregate(summaries, keys),
            "per_scene": {name: aggregate([s for s in summaries if s["scene"] == name], keys) for name in scene_names},
            "runs": summaries}


def run_bench(out: str | Path, suite: str | BenchSuite = "quick", *, executor: Any = None,
              scenes: Optional[dict[str, tuple[Path, int]]] = None, methods: Sequence[Method] = METHODS,
              iterations: Optional[int] = None, budget_minutes: Optional[float] = None,
              budget_step_cap: Optional[int] = None, train: Optional[dict] = None, command: str = "",
              priors: str = "ndn", on_outcome: Optional[Callable[[Any], None]] = None) -> dict:
    """Make (or reuse) the suite's scenes, run every method on each, write benchmarks.md/.json.

    ``priors``: the prior source of the prior-based rows (ndn, sfm or gt); ndn and sfm priors
    are computed for every scene that lacks them (:func:`ensure_priors`).

    ``scenes`` (name -> (folder, seed)) replaces the suite's generated scenes (tests,
    existing folders). ``iterations``, ``budget_minutes`` (0 = no equal-budget comparison)
    and ``budget_step_cap`` override the suite's (None = the suite's). ``executor``: an
    :class:`~.executor.Executor` (default: a local pool of one worker). Returns the report
    dict (also ``OUT/benchmarks.json``): the equal-step tables at the top level
    (``overall``, ``per_scene``, ``runs``) and the equal-budget ones under ``budget``
    (None without a budget).
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
    budget_minutes = suite.budget_minutes if budget_minutes is None else budget_minutes
    if budget_minutes < 0:
        raise ConfigError(f"budget_minutes must be >= 0, got {budget_minutes}")
    step_cap = budget_step_cap or suite.budget_step_cap or 2 * iterations
    if scenes is None:
        scenes = {f"{preset}_s{seed}": (make_scene(preset, seed, suite, out / "scenes"), seed)
                  for preset in suite.presets for seed in suite.seeds}
    if priors not in PRIOR_SOURCES:
        raise ConfigError(f"unknown prior source {priors!r}", hint=f"use one of {', '.join(PRIOR_SOURCES)}")
    if priors in COMPUTED_PRIOR_SOURCES and any(m.priors and not m.prior_source for m in methods):
        for folder, _ in scenes.values():
            ensure_priors(folder, priors)
    tasks, notes = plan_bench(scenes, out, iterations=iterations, methods=methods, train=train,
                              budget_minutes=budget_minutes, budget_step_cap=step_cap, priors=priors)
    # runs made with other settings are kept aside and trained again (RunTask.stale_settings)
    retrained = {}
    for task in tasks:
        stale = task.stale_settings()
        if stale and task.set_aside_if_stale() is not None:
            retrained[task.name] = stale
    if retrained:
        first, settings = next(iter(retrained.items()))
        notes.append(f"{len(retrained)} run(s) trained again because their saved settings differed from this bench's "
                     f"(e.g. {first}: {', '.join(settings[:4])}{' ...' if len(settings) > 4 else ''}); the old "
                     "folders are kept as *.stale-<time>")
    own_executor = executor is None
    executor = executor or LocalExecutor(1)
    try:
        outcomes = run_tasks(tasks, run_task, executor, retries=1, on_outcome=on_outcome)
    finally:
        if own_executor:
            executor.close()
    finished = [outcome for outcome in outcomes if outcome.status in ("done", "skipped")]
    failed = [{"run": outcome.task.name, "error": outcome.error or "", "attempts": outcome.attempts}
              for outcome in outcomes if outcome.status == "failed"]
    keys = [key for key, _, _ in QUALITY_COLUMNS + STEPS_COLUMN + COST_COLUMNS]
    budget_runs = [o.result for o in finished if o.task.config.get("max_minutes")]
    step_runs = [o.result for o in finished if not o.task.config.get("max_minutes")]
    budget = None
    if budget_minutes > 0:
        budget = {"budget_minutes": budget_minutes, "step_cap": step_cap,
                  **_comparison(budget_runs, list(scenes), keys)}
    report = {
        "suite": {"name": suite.name, "presets": list(suite.presets), "seeds": list(suite.seeds), "views": suite.views,
                  "resolution": suite.resolution, "samples": suite.samples, "points_per_view": suite.points_per_view,
                  "iterations": suite.iterations, "budget_minutes": suite.budget_minutes,
                  "budget_step_cap": suite.step_cap},
        "iterations": iterations, "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M"),
        "machine": machine_description(), "executor": type(executor).__name__, "command": command or "run_bench(...)",
        "priors": _prior_description(priors, scenes),
        **_comparison(step_runs, list(scenes), keys), "budget": budget, "notes": notes, "failed": failed,
    }
    atomic_write_json(out / "benchmarks.json", report)
    atomic_write_text(out / "benchmarks.md", bench_markdown(report))
    return report
