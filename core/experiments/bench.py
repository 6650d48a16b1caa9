"""The method comparison (``esgs bench``): 3DGS, Mip-Splatting, DropoutGS, PGSR, Scaffold-GS, 3DGS + GPDFN,
ESGS ablations and full ESGS on synthetic scenes, at equal step counts and at equal wall-clock
budgets, written as ``OUT/benchmarks.md``.

Scenes are made with ``esgs scene`` in a child process (Blender's ``bpy`` never enters
this process) and cached under ``OUT/scenes/<preset>_s<seed>_...``. By default the bench
then replaces the generator's exact surface samples by SfM points triangulated from the
rendered images with the known poses (:func:`.sfm_scene.make_sfm_scene`, as the demo and
the acceptance study do), cached in ``OUT/scenes/<...>_sfm``: the initial Gaussians, the
``sfm`` priors and the pinning of NDN depth then come from points a real capture would give.
Each (scene, method, seed) is one :class:`~.runs.RunTask` in ``OUT/runs/...`` (equal steps)
and, per budget, one more (equal training time: ``max_minutes`` with a step cap) in
``OUT/runs_budget/...`` for the shortest budget and ``OUT/runs_budget_<M>min/...`` for each longer
one (:func:`budget_plan`); tasks run through an :class:`~.executor.Executor` (local
process pool, or Ray), a failed run is retried once, and a restart repeats only unfinished
runs and runs whose saved settings differ from the ones the bench asks for now (a changed
default, another prior source, another scene folder).

The prior-based rows use the priors a user would have: ``auto`` by default (``priors="auto"``:
stereo labels, NDN and SfM fused per pixel with a confidence, computed once per scene and
kept in it), or any list of sources compared side by side (``priors=("auto", "labels",
"ndn")``: one full-ESGS row "ESGS (<source>)" per source; the ablation rows use the first).
One extra row, full ESGS with the generator's exact depth and normals, is labelled as the
upper bound: no real scene has those priors.

The equal-step runs evaluate their held-out views every ``eval_every`` steps (by default a
tenth of the run, :attr:`BenchSuite.eval_points`): from these curves the report gives, per
row, the training seconds to reach the 3DGS row's final held-out PSNR and SSIM on the same
scene and seed (:func:`.curves.time_to_baseline_quality`).
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
from .sfm_scene import SPARSE_POINTS
from .tables import COST_COLUMNS, QUALITY_COLUMNS, aggregate, markdown_table


@dataclass(frozen=True)
class BenchSuite:
    """Scenes (presets x seeds, rendered at ``resolution`` with ``views`` and ``samples``) and steps.

    ``eval_points``: held-out evaluations of each equal-step run (every ``iterations //
    eval_points`` steps, :meth:`eval_every`), the curves of the time-to-quality table; 0 = none."""

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
    eval_points: int = 10

    def eval_every(self, iterations: int = 0) -> int:
        """Steps between the evaluations of an equal-step run of ``iterations`` (0 = the suite's) steps."""
        iterations = iterations or self.iterations
        return max(1, iterations // self.eval_points) if self.eval_points > 0 else 0

    @property
    def step_cap(self) -> int:
        """Step cap of the budget runs (0 in the suite = twice the equal-step count)."""
        return self.budget_step_cap or 2 * self.iterations

    def scene_folder_name(self, preset: str, seed: int, sparse_points: str = "triangulated") -> str:
        """Cache key of a scene: everything that changes what ``esgs scene`` makes (``exact``:
        the rendered scene with the generator's points), or what the triangulated copy is made
        from (``triangulated``: ``..._sfm``; the generator's point count does not enter it)."""
        rendered = f"{preset}_s{seed}_{self.views}v_{self.resolution}_{self.samples}spp"
        if sparse_points == "triangulated":
            return f"{rendered}_sfm"
        return f"{rendered}_{self.points_per_view}p"


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
    fields set on the row (the published baselines run :data:`~esgs.core.train.config.VANILLA_3DGS`);
    ``per_source``: one row per prior source the bench compares (:func:`bench_rows`: key
    ``<key>_<source>``, ``label`` formatted with ``source``).

    A ``full`` row without ``priors`` is full ESGS with every prior dropped
    (:func:`full_esgs_without_priors`)."""

    key: str
    label: str
    method: str = "3dgs"
    settings: tuple = ()
    full: bool = False
    priors: bool = False
    prior_source: str = ""
    train: tuple = ()
    per_source: bool = False

    def method_config(self, source: str, scene: Path) -> Optional[dict]:
        """The row's ``method_config`` on ``scene`` with prior source ``source``."""
        from ..config import config_to_dict
        from ..methods import full_esgs

        if self.full and not self.priors:
            return full_esgs_without_priors(**dict(self.settings))
        if self.full:
            return config_to_dict(full_esgs(source, scene=scene, **dict(self.settings)))
        settings = dict(self.settings)
        if self.priors:
            settings["priors"] = source
        return settings or None


def _method(key: str, label: str, method: str = "3dgs", *, settings: Optional[dict] = None, full: bool = False,
            priors: Optional[bool] = None, prior_source: str = "", vanilla: bool = False,
            per_source: bool = False) -> Method:
    settings = settings or {}
    if priors is None:
        priors = full or bool(settings.get("depth") or settings.get("normal"))
    return Method(key, label, method, tuple(sorted(settings.items())), full, priors=priors,
                  prior_source=prior_source, train=tuple(sorted(VANILLA_3DGS.items())) if vanilla else (),
                  per_source=per_source)


def full_esgs_without_priors(**overrides: Any) -> dict:
    """What full ESGS (:func:`esgs.core.methods.full_esgs`) becomes when every prior is dropped:
    no prior source; depth, normal, consistency and sky losses off; GPDFN as the full method
    sets it (K = 3). The depth weight and the seeded points go back to ESGSConfig's defaults, so
    the row does not change with what a prior source would get. ``overrides``: ESGSConfig fields."""
    from ..config import config_from_dict, config_to_dict
    from ..methods import ESGSConfig, full_esgs

    settings = {**config_to_dict(full_esgs()), "priors": "", "depth": False, "normal": False, "consistency": False,
                "sky_weight": 0.0, "depth_weight": ESGSConfig.depth_weight,
                "prior_points": ESGSConfig.prior_points, **overrides}
    config = config_from_dict(ESGSConfig, settings)
    config.validate()
    return config_to_dict(config)


#: The sources a run on a synthetic scene can train with without a mesh step (the demo's too).
PRIOR_SOURCES = names(PriorSource.for_synthetic_scenes())
#: The sources ``esgs priors`` can compute for a scene that lacks them.
COMPUTED_PRIOR_SOURCES = names(PriorSource.computed())
#: ... and those :func:`ensure_priors` can (``labels``: ``esgs labels --reconstruct``, needs bpy).
ENSURED_PRIOR_SOURCES = (*COMPUTED_PRIOR_SOURCES, *names(tuple(s for s in PriorSource if s.made_by_labels)))
#: Where the prior-based rows may take their priors from (``--priors``, one or several): what
#: :func:`ensure_priors` makes, and the generator's exact maps.
PRIOR_CHOICES = (*ENSURED_PRIOR_SOURCES, *names(tuple(s for s in PriorSource if s.made_by_scene)))
#: The bench's prior source when none is named: the one users get (esgs train --esgs, the demo).
DEFAULT_PRIORS = ("auto",)
UPPER_BOUND_KEY = "esgs_full_gt"
#: The row whose final held-out quality the time-to-quality table measures the others against.
BASELINE_KEY = "3dgs"
#: The row of 3DGS as plain ``esgs train`` gives it (the sky model on): what ``--esgs`` is compared with.
DEFAULTS_KEY = "3dgs_sky"


#: The published baselines run as published (``vanilla``: constant background, no sky masks);
#: "3DGS + sky model" is plain 3DGS with this tool's defaults, so the table separates what the
#: sky model adds from what ESGS's priors add (every ESGS row uses the defaults). "3DGS + GPDFN"
#: is full ESGS with every prior dropped: what ESGS gives on a scene where no prior helps.
#: "ESGS (<source>)" is full ESGS, once per prior source the bench compares.
METHODS = (
    _method("3dgs", "3DGS", vanilla=True),
    _method("3dgs_sky", "3DGS + sky model (our defaults)"),
    _method("mip_splatting", "Mip-Splatting", "mip-splatting", vanilla=True),
    _method("dropout_gs", "DropoutGS", "dropout-gs", settings={"dropout_rate": 0.1}, vanilla=True),
    # the geometry specialist among the paper's baselines: planar Gaussians, no priors (docs/baselines.md)
    _method("pgsr", "PGSR", "pgsr", vanilla=True),
    # anchors decoding neural Gaussians per view, no priors; scored on its decoded Gaussians (docs/baselines.md)
    _method("scaffold_gs", "Scaffold-GS", "scaffold-gs", vanilla=True),
    _method("3dgs_gpdfn", "3DGS + GPDFN", "esgs", full=True, priors=False),
    _method("esgs_depth", "ESGS: depth prior", "esgs", settings={"depth": True}),
    _method("esgs_normal", "ESGS: normal prior", "esgs", settings={"normal": True}),
    _method("esgs_depth_normal", "ESGS: depth + normal", "esgs", settings={"depth": True, "normal": True}),
    _method("esgs_full", "ESGS ({source})", "esgs", full=True, per_source=True),
    # not a method a user can run on real data: the same ESGS fed the exact synthetic depth and normals
    _method(UPPER_BOUND_KEY, "ESGS, ground-truth priors (upper bound)", "esgs", full=True, prior_source="gt"),
)


def select_methods(keys: Optional[Sequence[str]]) -> tuple[Method, ...]:
    """The rows of :data:`METHODS` named by ``keys`` (``esgs bench --rows``), in the table's
    order; None or empty = every row. ConfigError naming the known keys for an unknown one."""
    if not keys:
        return METHODS
    known = [method.key for method in METHODS]
    unknown = [key for key in keys if key not in known]
    if unknown:
        raise ConfigError(f"unknown bench row(s) {', '.join(map(repr, unknown))}", hint=f"use some of {', '.join(known)}")
    return tuple(method for method in METHODS if method.key in set(keys))


def prior_sources(priors: str | Sequence[str]) -> tuple[str, ...]:
    """The bench's prior sources, in order, without repeats (``priors``: one name or several);
    ConfigError for an unknown one or none."""
    sources = (priors,) if isinstance(priors, str) else tuple(priors)
    sources = tuple(dict.fromkeys(str(source) for source in sources))
    if not sources:
        raise ConfigError("no prior source given", hint=f"use one or more of {', '.join(PRIOR_CHOICES)}")
    for source in sources:
        if source not in PRIOR_CHOICES:
            raise ConfigError(f"unknown prior source {source!r}", hint=f"use one or more of {', '.join(PRIOR_CHOICES)}")
    return sources


def bench_rows(methods: Sequence[Method], priors: str | Sequence[str]) -> list[tuple[Method, str]]:
    """Each row the bench trains with its prior source: a ``per_source`` method once per source
    of ``priors`` (key ``<key>_<source>``, its label formatted with the source), the others once
    with their own ``prior_source`` or else the first of ``priors``. A per-source row whose key
    is another method's (``esgs_full_gt`` = the upper bound) is that method's row."""
    import dataclasses

    sources = prior_sources(priors)
    keys = {method.key for method in methods}
    rows = []
    for method in methods:
        if not method.per_source:
            rows.append((method, method.prior_source or sources[0]))
            continue
        for source in sources:
            key = f"{method.key}_{source}"
            if key not in keys:
                rows.append((dataclasses.replace(method, key=key, label=method.label.format(source=source),
                                                 prior_source=source, per_source=False), source))
    return rows


def ensured_sources(methods: Sequence[Method], priors: str | Sequence[str]) -> list[str]:
    """The prior sources the bench's rows read that :func:`ensure_priors` can make, in order."""
    return list(dict.fromkeys(source for method, source in bench_rows(methods, priors)
                              if method.priors and source in ENSURED_PRIOR_SOURCES))


def ensure_priors(scene: Path, source: str) -> Path:
    """``SCENE/priors/<source>``, computed in a child process when the scene has none:
    ``esgs priors --method <source>`` (ndn, sfm, auto) or ``esgs labels --reconstruct``
    (labels: a mesh rebuilt from the images and poses, never the true mesh); ``gt`` priors
    come only from the generator.

    Both commands write the folder atomically, so an interrupted bench leaves either the
    whole folder or none, and a restart reuses it. A fused source (auto) is always asked
    for: its command reuses the folder while the images and sources it was made from hold,
    and fuses it again when one changed (labels computed since), here, once, rather than in
    each run that trains on it.
    """
    scene = Path(scene)
    folder = SceneDir(scene).prior(source)
    if source in available_priors(scene) and not PriorSource(source).fused:
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


def make_scene(preset: str, seed: int, suite: BenchSuite, scenes_dir: Path,
               sparse_points: str = "triangulated") -> Path:
    """The bench's scene of ``preset`` and ``seed``, made unless it is there (each folder appears complete).

    ``esgs scene`` renders into ``scenes_dir/<...>_<points>p`` (with the generator's exact
    surface samples as its SfM points); ``sparse_points="exact"`` returns that folder.
    ``"triangulated"`` (the default) copies it to ``scenes_dir/<...>_sfm`` with SfM points
    triangulated from the rendered images with the known poses and their ``sfm`` priors
    (:func:`.sfm_scene.make_sfm_scene`); DatasetError when no point can be triangulated.
    """
    from ..errors import DatasetError
    from ..terrain.scene_job import SceneJob, parse_resolution, render_scene
    from .sfm_scene import make_sfm_scene

    if sparse_points not in SPARSE_POINTS:
        raise ConfigError(f"unknown sparse points {sparse_points!r}", hint=f"use one of {', '.join(SPARSE_POINTS)}")
    rendered = Path(scenes_dir) / suite.scene_folder_name(preset, seed, "exact")
    folder = Path(scenes_dir) / suite.scene_folder_name(preset, seed, sparse_points)
    if SceneDir(folder).has_model():
        return folder
    if not SceneDir(rendered).has_model():
        width, height = parse_resolution(suite.resolution)
        job = SceneJob(preset=preset, seed=seed, views=suite.views, width=width, height=height,
                       samples=suite.samples, points_per_view=suite.points_per_view)
        try:
            render_scene(job, rendered)
        except ESGSError as error:
            raise type(error)(f"esgs scene failed for {preset} seed {seed}: {error.message}",
                              path=error.path or rendered, hint=error.hint) from error
    if folder == rendered:
        return folder
    try:
        make_sfm_scene(rendered, folder)
    except DatasetError as error:
        raise DatasetError(f"no SfM points for {preset} seed {seed}: {error.message}", path=error.path or rendered,
                           hint="render more views or a larger resolution, or run the bench with --sparse-points "
                                "exact (the generator's surface samples, which flatter every method)") from error
    return folder


@dataclass(frozen=True)
class Budget:
    """One equal-budget comparison: ``minutes`` of training per run, at most ``step_cap`` steps
    (the cap also sets the schedules), run folders under ``OUT/<folder>``, task names ending in
    ``suffix``."""

    minutes: float
    step_cap: int
    folder: str
    suffix: str


def budget_list(budget_minutes: float | Sequence[float]) -> tuple[float, ...]:
    """The budgets in minutes, in the order given, without repeats or zeros (0 alone = none);
    ConfigError for a negative one."""
    values = (budget_minutes,) if isinstance(budget_minutes, (int, float)) else tuple(budget_minutes)
    for value in values:
        if float(value) < 0:
            raise ConfigError(f"budget_minutes must be >= 0, got {value:g}",
                              hint="give training minutes per budget run, e.g. --budget-minutes 1 5 (0 = none)")
    return tuple(dict.fromkeys(float(value) for value in values if float(value) > 0))


def budget_plan(budget_minutes: float | Sequence[float], step_cap: int) -> list[Budget]:
    """The equal-budget comparisons, shortest first, whatever the order given: the shortest
    budget's runs in ``runs_budget`` (task suffix ``@budget``, the folders of a bench with one
    budget), each longer one's in ``runs_budget_<M>min`` (``@<M>min``). ``step_cap`` is the
    shortest budget's cap; a longer budget gets it scaled by its minutes over the shortest's (a
    5-minute run on the schedule of a 1-minute cap would end its schedule early and then train on
    at the final learning rates). ConfigError for budgets too close to get folders of their own."""
    minutes = sorted(budget_list(budget_minutes))
    if not minutes:
        return []
    first = minutes[0]
    plans = [Budget(first, int(step_cap), "runs_budget", "@budget")]
    for value in minutes[1:]:
        plans.append(Budget(value, max(1, round(step_cap * value / first)), f"runs_budget_{value:g}min",
                            f"@{value:g}min"))
    names = [f"{value:g}" for value in minutes]
    if len(set(names)) < len(names):
        raise ConfigError(f"budgets of {', '.join(repr(value) for value in minutes)} minutes are too close to tell "
                          "apart", hint="give budgets that differ in their first six digits, e.g. --budget-minutes 1 5")
    return plans


def budget_of(task: RunTask, out: Path, budgets: Sequence[Budget]) -> Optional[Budget]:
    """The budget whose folder holds ``task``'s run (:func:`plan_bench`), None for an equal-step run."""
    folder = Path(task.out).parent.parent
    return next((budget for budget in budgets if folder == Path(out) / budget.folder), None)


def plan_bench(scenes: dict[str, tuple[Path, int]], out: Path, *, iterations: int, methods: Sequence[Method] = METHODS,
               train: Optional[dict] = None, budget_minutes: float | Sequence[float] = 0.0, budget_step_cap: int = 0,
               priors: str | Sequence[str] = DEFAULT_PRIORS, eval_every: int = 0) -> tuple[list[RunTask], list[str]]:
    """Run tasks for every scene (name -> (folder, seed)) and row, and notes on what was left out.

    ``priors``: one prior source or several (:func:`bench_rows`): full ESGS runs once per
    source ("ESGS (<source>)"); the other prior-based rows read ``priors/<first source>`` (a
    method's own ``prior_source`` wins, e.g. the gt upper bound). A scene without the maps a
    row needs skips it with a note.

    Equal-step tasks train ``iterations`` steps in ``OUT/runs/<scene>/<method>``. For each
    budget of ``budget_minutes`` (one number or several; 0 = none) every method also trains for
    that much training time (``max_minutes``) in the budget's folder (:func:`budget_plan`: the
    shortest in ``OUT/runs_budget/<scene>/<method>``), up to its step cap (``budget_step_cap``, 0 =
    twice ``iterations``, for the shortest budget, scaled by the minutes for the others); its
    learning-rate and densification schedules are those of the cap.
    ``eval_every`` > 0: the equal-step runs evaluate their held-out views every so many steps
    (``TrainConfig.eval_every``; the curves of the time-to-quality table).
    """
    tasks, notes = [], []
    modes = [("", "runs", {"iterations": iterations, **({"eval_every": int(eval_every)} if eval_every else {})})]
    for budget in budget_plan(budget_minutes, budget_step_cap or 2 * iterations):
        modes.append((budget.suffix, budget.folder, {"iterations": budget.step_cap, "max_minutes": budget.minutes}))
    rows = bench_rows(methods, priors)
    for scene_name, (folder, seed) in scenes.items():
        found = available_priors(folder)
        mesh = SceneDir(folder).ground_truth_mesh
        for method, source in rows:
            method_config = method.method_config(source, folder)
            if method.priors:
                needed = {kind for kind in ("depth", "normal") if (method_config or {}).get(kind)}
                if not needed <= found.get(source, set()):
                    notes.append(f"{method.label} skipped on {scene_name}: no {source} "
                                 f"{'/'.join(sorted(needed))} priors")
                    continue
            for suffix, folder_name, schedule in modes:
                config = {**(train or {}), **dict(method.train), **schedule, "seed": seed,
                          "method": method.method, "method_config": method_config}
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
    from .paired import paired_markdown

    extra = STEPS_COLUMN if part.get("budget_minutes") else ()
    lines = [f"## {title}: all scenes", "", markdown_table(part["overall"], QUALITY_COLUMNS), "",
             markdown_table(part["overall"], extra + COST_COLUMNS)]
    for baseline, rows in (part.get("paired") or {}).items():
        if rows:
            lines += [f"### {title}: each method against {baseline} on the same scene and seed", "",
                      f"Per run, the method's figure minus {baseline}'s on the same scene and seed (the distance: "
                      "its ratio), mean ± std over the runs, and in how many runs the method did better. **Bold**: "
                      "better beyond the spread (the mean is more than one std from no change); _italic_: worse "
                      "beyond it.", "", paired_markdown(rows)]
    for scene_name, rows in part["per_scene"].items():
        lines += [f"### {title}: {scene_name}", "", markdown_table(rows, QUALITY_COLUMNS + extra + COST_COLUMNS)]
    return lines


#: (figure, column title, decimals) of the time-to-quality table.
TIME_TO_QUALITY_COLUMNS = (("to_psnr_s", "to its PSNR (s)", 1), ("to_ssim_s", "to its SSIM (s)", 1),
                           ("to_quality_s", "to both (s)", 1), ("ratio", "both / its train time", 2))


def _time_cell(stats: dict, decimals: int, reached: int, runs: int) -> str:
    """``mean ± std`` over the runs that reached the target, with how many did when not all."""
    from .tables import format_cell

    if not stats.get("n"):
        return "not reached"
    cell = format_cell(stats, decimals)
    return cell if stats["n"] == runs else f"{cell} ({stats['n']}/{runs} reached)"


def _time_to_baseline_table(rows: Sequence[dict]) -> str:
    titles = ["method", "runs", "its train time (s)", *(title for _, title, _ in TIME_TO_QUALITY_COLUMNS)]
    lines = ["| " + " | ".join(titles) + " |", "|" + "---|" * len(titles)]
    for row in rows:
        cells = [str(row["variant"]), str(row["runs"]), _time_cell(row["baseline_s"], 1, row["runs"], row["runs"])]
        cells += [_time_cell(row[key], decimals, row["reached"], row["runs"]) for key, _, decimals in
                  TIME_TO_QUALITY_COLUMNS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _time_to_baseline_markdown(part: dict, iterations: int) -> list[str]:
    """The time-to-quality tables: all scenes, then each scene."""
    baseline = part["baseline"]
    every = part.get("eval_every") or 0
    sparse = [run for run in part["runs"] if run["points"] < 2]
    lines = [f"## Time to {baseline}'s quality: all scenes", "",
             f"Training seconds each method's {iterations}-step run takes to reach the final held-out PSNR and SSIM "
             f"of the {baseline} run on the same scene and seed (\"its\" below: {baseline}'s), from the runs' "
             "evaluation curves "
             + (f"(held-out views evaluated every {every} steps, evaluation time not counted; " if every else
                "(no evaluation during the runs: each run's end-of-run evaluation only; ")
             + "the crossing interpolated linearly between the two evaluations around it). 'to both': when the "
             f"later of the two is reached; the last column divides it by {baseline}'s own training time. Mean "
             "± std over the runs that reached it; 'not reached' when none did.", ""]
    if sparse:
        lines += [f"{len(sparse)} run(s) have a single evaluation (trained without an evaluation curve): their "
                  "time is their whole training time when they reach the target.", ""]
    if part.get("missing_baseline"):
        lines += [f"No {baseline} run to measure against on: {', '.join(part['missing_baseline'])}.", ""]
    lines.append(_time_to_baseline_table(part["overall"]))
    for scene_name, rows in part["per_scene"].items():
        lines += [f"### Time to {baseline}'s quality: {scene_name}", "", _time_to_baseline_table(rows)]
    return lines


def _made_by(source: str, weights: Sequence[str]) -> str:
    """What the priors of ``source`` are, for the report."""
    ndn_weights = f"weights {', '.join(weights or ['shipped'])}"
    return {"auto": "the `auto` priors (`esgs priors --method auto`): stereo labels where they agree with the "
                    f"SfM points, NDN ({ndn_weights}) pinned to the SfM points in their holes, the SfM depth as the "
                    "floor, each pixel's confidence scaling the prior losses",
            "labels": "stereo labels (`esgs labels --reconstruct`: a mesh rebuilt from the images and poses by "
                      "multi-view stereo, rendered)",
            "ndn": f"NDN's relative depth and normals (`esgs priors --method ndn`, {ndn_weights}), pinned to each "
                   "view's SfM points",
            "sfm": "the sparse SfM depth (`esgs priors --method sfm`)",
            "gt": "the generator's exact depth and normals"}[source]


def _priors_sentence(priors: Optional[dict]) -> str:
    priors = priors or {}
    sources = list(priors.get("sources") or [priors.get("source", "gt")])
    weights = priors.get("weights") or []
    if len(sources) == 1:
        sentence = f"Priors: the ESGS rows use {_made_by(sources[0], weights)}."
    else:
        # gt's full-ESGS row is the labelled upper bound (bench_rows)
        rows = ", ".join(f"'ESGS ({source})'" for source in sources if source != "gt")
        sentence = (f"Priors: the rows {rows} train full ESGS on each source: "
                    + "; ".join(f"{source}: {_made_by(source, weights)}" for source in sources)
                    + f". The ablation rows (ESGS: depth prior, normal prior, depth + normal) use {sources[0]}.")
    if sources != ["gt"]:
        sentence += (" The row 'ESGS, ground-truth priors (upper bound)' is the same full ESGS fed the generator's "
                     "exact depth and normals: a bound on what a perfect prior would give, not a method a user can "
                     "run on real data.")
    return sentence


def _sparse_points_sentence(sparse: Optional[dict], points_per_view: int) -> str:
    """Where the scenes' SfM points come from, for the report (old reports: the generator's)."""
    sparse = sparse or {"kind": "exact"}
    exact = (f"the generator's exact surface samples ({points_per_view} per view), which flatter every method's "
             "geometry")
    if sparse["kind"] == "exact":
        return exact
    points = list((sparse.get("points") or {}).values())
    triangulated = ("triangulated from the rendered images with the known poses (SIFT matches, pycolmap"
                    + (f"; {min(points)}-{max(points)} points per scene" if points else "")
                    + (f", mean reprojection error {sparse['mean_reprojection_error_px']:.2f} px"
                       if sparse.get("mean_reprojection_error_px") is not None else "")
                    + "), as a real capture gives them")
    if sparse["kind"] == "triangulated":
        return triangulated
    return f"{triangulated} on {len(points)} scenes; {exact} on the others"


def report_budgets(report: dict) -> list[dict]:
    """The equal-budget comparisons of a bench report, in order (reports before several budgets
    have only ``budget``: one or None)."""
    if report.get("budgets") is not None:
        return list(report["budgets"])
    return [report["budget"]] if report.get("budget") else []


def bench_markdown(report: dict) -> str:
    """docs-style Markdown of a bench report (see :func:`run_bench`)."""
    suite = report["suite"]
    machine = report["machine"]
    budgets = report_budgets(report)
    lines = [f"# Benchmarks: {suite['name']} suite", "",
             f"Date (UTC): {report['date']}. Machine: {machine['platform']}, {machine['processor']}, "
             f"{machine['cpu_count']} logical CPUs, Python {machine['python']}, torch {machine['torch']}, "
             f"GPU: {machine['gpu'] or 'none'}. Executor: {report['executor']}.", "",
             f"Scenes: `esgs scene` presets {', '.join(suite['presets'])} x seeds "
             f"{', '.join(map(str, suite['seeds']))} ({suite['views']} views, {suite['resolution']}, "
             f"{suite['samples']} samples); SfM points (the initial Gaussians, the sfm priors, the pinning of NDN "
             f"depth): {_sparse_points_sentence(report.get('sparse_points'), suite['points_per_view'])}; every "
             f"method trains with the same seed as its scene, {report['iterations']} steps for the equal-step "
             "comparison"
             + (" and " + ", ".join(f"{budget['budget_minutes']:g} minutes of training (at most {budget['step_cap']} "
                                    "steps)" for budget in budgets)
                + f" for the equal-budget one{'s' if len(budgets) > 1 else ''} (the schedules of the cap)"
                if budgets else "")
             + ". Quality on the held-out "
             "views (every 8th image); distances from the Gaussian centres with opacity >= 0.5 to "
             "mesh/ground_truth.ply (scene units, metres). Train time is training only; peak RSS is the run's "
             "process (ru_maxrss); render time is one held-out frame, mean over the held-out views. "
             "Mean ± std over scenes and seeds.", "",
             _priors_sentence(report.get("priors")), ""]
    auto = (report.get("priors") or {}).get("auto") or {}
    if auto:
        lines += [f"- {scene_name}: {line}" for scene_name, line in auto.items()] + [""]
    lines += [f"Command: `{report['command']}`", ""]
    lines += _comparison_markdown(report, f"At equal step count ({report['iterations']} steps)")
    for budget in budgets:
        lines += ["", *_comparison_markdown(budget, f"At equal wall-clock budget ({budget['budget_minutes']:g} min)")]
    for part in ("time_to_baseline", "time_to_defaults"):
        if report.get(part):
            lines += ["", *_time_to_baseline_markdown(report[part], report["iterations"])]
    if report["notes"] or report["failed"]:
        lines += ["## Notes", ""]
        lines += [f"- {note}" for note in report["notes"]]
        lines += [f"- FAILED {item['run']} after {item['attempts']} attempts: {item['error'].splitlines()[0]}"
                  for item in report["failed"]]
        lines.append("")
    return "\n".join(lines)


def _prior_description(sources: Sequence[str], scenes: dict[str, tuple[Path, int]]) -> dict[str, Any]:
    """The prior sources of the bench (``source``: the first, the ablation rows'); for NDN and
    auto the weights NDN's maps were computed with (the ``weights`` header of each scene's
    first NDN depth map); for auto one line per scene on what its priors are made of."""
    from ..formats.imageio import read_exr

    weights, auto = set(), {}
    if {"ndn", "auto"} & set(sources):
        for folder, _ in scenes.values():
            for path in sorted(SceneDir(folder).prior_maps("ndn", "depth").glob("*.exr"))[:1]:
                try:
                    weights.add(Path(read_exr(path)[1].get("weights", "")).name)
                except (OSError, ValueError, ESGSError):
                    pass  # the description is informative only; the run itself checks the maps
    if "auto" in sources:
        from ..priors.auto import read_report, summary_line

        for scene_name, (folder, _) in scenes.items():
            report = read_report(Path(folder))
            try:
                if report:
                    auto[scene_name] = summary_line(report)
            except (KeyError, TypeError, ValueError):
                pass  # informative only, as above
    return {"source": sources[0], "sources": list(sources), "weights": sorted(w for w in weights if w), "auto": auto}


def _sparse_points_description(scenes: dict[str, tuple[Path, int]]) -> dict[str, Any]:
    """How the scenes' SfM points were made, from each ``scene.json``'s ``sparse_points``
    record (:func:`.sfm_scene.make_sfm_scene`): ``kind`` triangulated, exact or mixed, the
    triangulated point count per scene and their mean reprojection error."""
    import json

    records = {}
    for scene_name, (folder, _) in scenes.items():
        path = SceneDir(folder).provenance
        try:
            record = json.loads(path.read_text()).get("sparse_points") if path.is_file() else None
        except (OSError, ValueError):
            record = None
        records[scene_name] = record if isinstance(record, dict) and record.get("points") else None
    triangulated = {name: record for name, record in records.items() if record}
    kind = "exact" if not triangulated else "triangulated" if len(triangulated) == len(records) else "mixed"
    errors = [record.get("mean_reprojection_error_px") for record in triangulated.values()]
    errors = [float(e) for e in errors if e is not None]
    return {"kind": kind, "points": {name: int(record["points"]) for name, record in triangulated.items()},
            "mean_reprojection_error_px": sum(errors) / len(errors) if errors else None}


#: The rows every other row is paired with in the reports' paired tables, when they ran.
PAIRED_BASELINE_KEYS = (BASELINE_KEY, DEFAULTS_KEY)


def _comparison(summaries: list[dict], scene_names: Sequence[str], keys: Sequence[str]) -> dict:
    """Rows over all scenes and per scene (mean ± std over seeds) of one set of run summaries,
    and each row paired with the 3DGS rows on the same scene and seed (``paired``: baseline
    label -> :func:`.paired.paired_rows`)."""
    from .paired import paired_rows

    labels = [method.label for method in METHODS if method.key in PAIRED_BASELINE_KEYS]
    ran = {summary.get("variant") for summary in summaries}
    return {"overall": aggregate(summaries, keys),
            "per_scene": {name: aggregate([s for s in summaries if s["scene"] == name], keys) for name in scene_names},
            "paired": {label: paired_rows(summaries, label) for label in labels if label in ran},
            "runs": summaries}


def _time_to_baseline(outcomes: Sequence[Any], eval_every: int, key: str = BASELINE_KEY) -> Optional[dict]:
    """The time-to-quality figures of the finished equal-step runs (their curves read from
    their folders) against the ``key`` row (:data:`BASELINE_KEY`, or :data:`DEFAULTS_KEY`:
    what plain ``esgs train`` gives); None without such a run."""
    from .curves import read_eval_curve, time_to_baseline_quality

    runs = [{"key": o.task.name.rpartition("/")[2], "variant": o.task.variant, "scene": o.task.scene_name,
             "seed": o.task.seed, "curve": read_eval_curve(o.task.out)} for o in outcomes]
    baseline = [run for run in runs if run["key"] == key]
    if not baseline:
        return None
    figures = time_to_baseline_quality(runs, key)
    return {"baseline": baseline[0]["variant"], "eval_every": eval_every, **figures}


def run_bench(out: str | Path, suite: str | BenchSuite = "quick", *, executor: Any = None,
              scenes: Optional[dict[str, tuple[Path, int]]] = None, methods: Sequence[Method] = METHODS,
              iterations: Optional[int] = None, budget_minutes: Optional[float | Sequence[float]] = None,
              budget_step_cap: Optional[int] = None, train: Optional[dict] = None, command: str = "",
              priors: str | Sequence[str] = DEFAULT_PRIORS, sparse_points: str = "triangulated",
              eval_every: Optional[int] = None, on_outcome: Optional[Callable[[Any], None]] = None) -> dict:
    """Make (or reuse) the suite's scenes, run every method on each, write benchmarks.md/.json.

    ``priors``: the prior source(s) of the prior-based rows (:data:`PRIOR_CHOICES`; several:
    one full-ESGS row per source, see :func:`bench_rows`); every source but gt is made for
    every scene that lacks it (:func:`ensure_priors`; the fused auto last, from the others).
    ``sparse_points``: the suite's scenes get SfM points triangulated from their images
    (default) or keep the generator's exact ones (:func:`make_scene`).

    ``scenes`` (name -> (folder, seed)) replaces the suite's generated scenes (tests,
    existing folders). ``iterations``, ``budget_minutes`` (one number or several, one
    equal-budget comparison each; 0 = none) and ``budget_step_cap`` (the shortest budget's cap,
    :func:`budget_plan`) override the suite's (None = the suite's). ``eval_every``: steps
    between the held-out evaluations of the equal-step runs (None = the suite's,
    :meth:`BenchSuite.eval_every`; 0 = none, the time-to-quality table then has each run's
    end-of-run evaluation only). ``executor``: an
    :class:`~.executor.Executor` (default: a local pool of one worker). Returns the report
    dict (also ``OUT/benchmarks.json``): the equal-step tables at the top level
    (``overall``, ``per_scene``, ``paired``, ``runs``), the equal-budget ones under ``budgets``
    (a list, one per budget, shortest first; reports from before several budgets had one
    ``budget``: read either with :func:`report_budgets`), and the time to the 3DGS row's quality under
    ``time_to_baseline`` (None without a 3DGS row).
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
    budget_minutes = budget_list(suite.budget_minutes if budget_minutes is None else budget_minutes)
    step_cap = budget_step_cap or suite.budget_step_cap or 2 * iterations
    eval_every = suite.eval_every(iterations) if eval_every is None else int(eval_every)
    if eval_every < 0:
        raise ConfigError(f"eval_every must be >= 0, got {eval_every}")
    sources = prior_sources(priors)
    if sparse_points not in SPARSE_POINTS:
        raise ConfigError(f"unknown sparse points {sparse_points!r}", hint=f"use one of {', '.join(SPARSE_POINTS)}")
    if scenes is None:
        scenes = {f"{preset}_s{seed}": (make_scene(preset, seed, suite, out / "scenes", sparse_points), seed)
                  for preset in suite.presets for seed in suite.seeds}
    # the sources auto is fused from first, so it is fused once, from all of them
    for source in sorted(ensured_sources(methods, sources), key=lambda name: PriorSource(name).fused):
        for folder, _ in scenes.values():
            ensure_priors(folder, source)
    tasks, notes = plan_bench(scenes, out, iterations=iterations, methods=methods, train=train,
                              budget_minutes=budget_minutes, budget_step_cap=step_cap, priors=sources,
                              eval_every=eval_every)
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
    plans = budget_plan(budget_minutes, step_cap)
    budget_of_run = [budget_of(o.task, out, plans) for o in finished]
    equal_steps = [o for o, budget in zip(finished, budget_of_run) if budget is None]
    step_runs = [o.result for o in equal_steps]
    budgets = [{"budget_minutes": budget.minutes, "step_cap": budget.step_cap,
                **_comparison([o.result for o, its in zip(finished, budget_of_run) if its == budget],
                              list(scenes), keys)}
               for budget in plans]
    report = {
        "suite": {"name": suite.name, "presets": list(suite.presets), "seeds": list(suite.seeds), "views": suite.views,
                  "resolution": suite.resolution, "samples": suite.samples, "points_per_view": suite.points_per_view,
                  "iterations": suite.iterations, "budget_minutes": suite.budget_minutes,
                  "budget_step_cap": suite.step_cap, "sparse_points": sparse_points},
        "iterations": iterations, "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M"),
        "machine": machine_description(), "executor": type(executor).__name__, "command": command or "run_bench(...)",
        "priors": _prior_description(sources, scenes), "sparse_points": _sparse_points_description(scenes),
        **_comparison(step_runs, list(scenes), keys), "budgets": budgets,
        "time_to_baseline": _time_to_baseline(equal_steps, eval_every),
        # against 3DGS as users get it from plain `esgs train` (the comparison of `--esgs`)
        "time_to_defaults": _time_to_baseline(equal_steps, eval_every, DEFAULTS_KEY),
        "notes": notes, "failed": failed,
    }
    atomic_write_json(out / "benchmarks.json", report)
    atomic_write_text(out / "benchmarks.md", bench_markdown(report))
    return report
