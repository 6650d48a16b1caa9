"""The acceptance study of ESGS (issue #6): 3DGS vs full ESGS on sparse-view scenes, and the sky fix.

    .venv/bin/python benchmarks/esgs_acceptance.py --out /work/runs/esgs_acceptance \
        --preset cratered_plain --preset rocky_slope [--scene mars=PATH] --sky-preset rover_horizon \
        --views 10 --resolution 320x180 --seeds 0 1 2 --iterations 400 --width 160 --threads 1 \
        --doc docs/esgs_acceptance.md

Steps (each cached, so the script can be stopped and started again):

1. ``esgs scene --preset P --views V --resolution WxH --sfm`` into ``OUT/scenes/<P>`` (or the
   given ``--scene NAME=PATH``);
2. :func:`esgs.core.experiments.sfm_scene.make_sfm_scene` into ``OUT/scenes/<name>_sfm``:
   the same scene with sparse points triangulated from the images (known poses) and their
   ``sfm`` priors; the sky scene also gets the ``gt_skyfilled`` prior (core/experiments/sky.py);
3. the runs, one after another, seed first (3DGS and ESGS with every prior source; on the
   sky scene ESGS with ``gt_skyfilled`` with masks honoured and ignored), each followed by a
   rewrite of the report (``OUT/acceptance.json`` and ``--doc``).

``--max-minutes M`` compares at equal training time instead of equal steps (issue #26's first
target on these scenes): every run trains M minutes, off the clock of its evaluation, with
``--iterations`` as its step cap and schedule length, as ``esgs bench``'s budget runs do (use its
own ``--out``; run it on an otherwise idle machine or beside runs of the same load).

``--baselines pgsr scaffold-gs`` (opt-in; any published baseline of ``esgs bench``) adds a row
per method to every scene of the main study: run as published, like the bench's rows
(constant background, no sky masks, no priors), with the 3DGS arm's steps, seeds and width;
each ESGS row is then also compared with each of them by the same criteria.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

# idle OpenMP threads spin by default and take the cores a busy machine's other runs need
# (docs/rasterizer.md, "Spinning OpenMP workers"); set before torch loads
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from esgs.core.experiments.acceptance import SOURCES, plan_runs, scene_rows, verdict  # noqa: E402
from esgs.core.experiments.bench import ensure_priors  # noqa: E402
from esgs.core.config import config_to_dict  # noqa: E402
from esgs.core.experiments.runs import RunTask, run_task  # noqa: E402
from esgs.core.methods import full_esgs  # noqa: E402
from esgs.core.experiments.sfm_scene import make_sfm_scene  # noqa: E402
from esgs.core.experiments.sky import sky_figures, write_sky_filled_priors  # noqa: E402
from esgs.core.experiments.tables import QUALITY_COLUMNS, aggregate, format_cell, markdown_table  # noqa: E402
from esgs.core.io_utils import atomic_write_json, atomic_write_text  # noqa: E402
from esgs.core.formats.scene_dir import PriorSource, SceneDir  # noqa: E402

SKY_KEYS = ("psnr", "psnr_sky", "psnr_surface", "alpha_sky", "horizon_depth_error", "distance_mean")


def make_scene(preset: str, out: Path, views: int, resolution: str) -> Path:
    if not out.is_dir():
        subprocess.run([sys.executable, "-m", "esgs.core.cli", "scene", "--preset", preset, "--views", str(views),
                        "--resolution", resolution, "--samples", "16", "--sfm", "--out", str(out)], check=True)
    return out


def sfm_variant(scene: Path, root: Path, name: str) -> Path:
    out = root / f"{name}_sfm"
    if not out.is_dir():
        record = make_sfm_scene(scene, out)
        print(f"{name}: {record['points']} triangulated points, {record['mean_reprojection_error_px']:.2f} px", flush=True)
    return out


def sky_arms(prior: str, sky_weights: tuple[float, ...] = (), ignore_masks: bool = True) -> list[tuple[str, str, dict]]:
    """ESGS on the sky scene with ``prior``: masks honoured (the fix), masks honoured plus the
    sky loss at each weight of ``sky_weights`` (sky pushed beyond the far surface), masks ignored."""
    name, key = ("gt, sky filled", "skyfilled") if prior == PriorSource.GT_SKYFILLED else (prior, prior)
    esgs = config_to_dict(full_esgs(prior, normal=True, consistency=False))  # every source here has normals
    # the mask arms without the sky loss, whatever its default: they measure the masks alone
    arms = [(f"ESGS ({name}), masks honoured", f"esgs-{key}-masks", {**esgs, "use_masks": True, "sky_weight": 0.0})]
    arms += [(f"ESGS ({name}), masks + sky loss {weight:g}", f"esgs-{key}-masks-sky{weight:g}",
              {**esgs, "use_masks": True, "sky_weight": weight}) for weight in sky_weights if weight > 0]
    if ignore_masks:
        arms.append((f"ESGS ({name}), masks ignored", f"esgs-{key}-nomasks",
                     {**esgs, "use_masks": False, "sky_weight": 0.0}))
    return arms


def sky_tasks(scene: Path, out: Path, iterations: int, seeds, train: dict, baseline: bool = True,
              priors: tuple[str, ...] = (PriorSource.GT_SKYFILLED,), sky_weights: tuple[float, ...] = (),
              ignore_masks: bool = True) -> list[RunTask]:
    tasks = []
    mesh = SceneDir(scene).ground_truth_mesh
    arms = [("3DGS", "3dgs", {})] if baseline else []
    for prior in priors:
        arms += sky_arms(prior, sky_weights, ignore_masks)
    for seed in seeds:
        for label, key, esgs in arms:
            config = {**train, "iterations": iterations, "seed": seed,
                      "method": "esgs" if esgs else "3dgs", "method_config": esgs or None}
            tasks.append(RunTask(name=f"sky/{key}/seed{seed}", scene=scene, out=out / "runs" / "sky" / key / f"seed{seed}",
                                 config=config, variant=label, seed=seed, scene_name="sky", mesh=mesh,
                                 measure_render=False))
    return tasks


def baseline_rows(names) -> list:
    """The rows of ``esgs bench`` (:data:`esgs.core.experiments.bench.METHODS`) of the published
    baselines named by their training method (``pgsr``, ``scaffold-gs``, ...), each once, in the
    order given; ConfigError for a name that is not one."""
    from esgs.core.errors import ConfigError
    from esgs.core.experiments.bench import METHODS

    offered = baseline_choices()
    rows = {row.method: row for row in METHODS if row.method in offered}
    for name in names:
        if name not in rows:
            raise ConfigError(f"--baselines {name!r}: not a published baseline of esgs bench",
                              hint=f"choose among {', '.join(offered)}")
    return [rows[name] for name in dict.fromkeys(names)]


def baseline_choices() -> tuple[str, ...]:
    """Training methods of the bench's published baselines (its rows run as published) other than 3DGS."""
    from esgs.core.experiments.bench import METHODS

    return tuple(dict.fromkeys(row.method for row in METHODS if row.train and row.method != "3dgs"))


def baseline_tasks(scenes: dict, out: Path, *, iterations: int, seeds, train: dict, names) -> list[RunTask]:
    """The ``--baselines`` rows: each method with the bench's settings, run as published
    (:data:`~esgs.core.train.config.VANILLA_3DGS` over ``train``), with the 3DGS arm's steps and
    seeds, seed first; runs in ``OUT/runs/<scene>/<bench key>/seed<k>`` beside the study's."""
    tasks = []
    rows = baseline_rows(names)
    for seed in seeds:
        for name, scene in scenes.items():
            mesh = SceneDir(scene).ground_truth_mesh
            for row in rows:
                config = {**train, **dict(row.train), "iterations": iterations, "seed": seed,
                          "method": row.method, "method_config": row.method_config("", Path(scene))}
                tasks.append(RunTask(name=f"{name}/{row.key}/seed{seed}", scene=Path(scene),
                                     out=Path(out) / "runs" / name / row.key / f"seed{seed}", config=config,
                                     variant=row.label, seed=seed, scene_name=name,
                                     mesh=mesh if mesh.is_file() else None, measure_render=False))
    return tasks


def esgs_options(items: list[str]) -> dict:
    """``["depth_weight=3", ...]`` -> ``{"depth_weight": 3.0}``, checked against ESGSConfig's fields."""
    import dataclasses

    from esgs.core.errors import ConfigError
    from esgs.core.methods.esgs.config import ESGSConfig

    fields = {field.name: field for field in dataclasses.fields(ESGSConfig)}
    defaults = ESGSConfig()
    options = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or key not in fields:
            raise ConfigError(f"--esgs-option {item!r}: expected KEY=VALUE with KEY one of {', '.join(fields)}")
        kind = type(getattr(defaults, key))
        options[key] = text.lower() in ("1", "true", "yes") if kind is bool else kind(text)
    return options


def ensure_computed_priors(scene: Path, source: str) -> None:
    """``source`` priors for ``scene`` unless it has them (the bench's rule, in a child process:
    ``esgs priors --method ndn`` with ``$ESGS_NDN_WEIGHTS`` or the shipped weights; ``esgs
    labels --reconstruct`` for labels, from the images and the triangulated poses only)."""
    if not SceneDir(scene).prior(source).is_dir():
        ensure_priors(scene, source)
        print(f"{scene.name}: wrote {source} priors", flush=True)


def with_sky_figures(task: RunTask, summary: dict) -> dict:
    cache = Path(task.out) / "sky.json"
    if not cache.is_file():
        atomic_write_json(cache, sky_figures(task.out, task.scene))
    return {**summary, **json.loads(cache.read_text())}


def report(args, scenes: dict, summaries: list[dict], sky: list[dict], failed: list[str], started: float) -> None:
    rows = scene_rows(summaries)
    baselines = [row.label for row in baseline_rows(getattr(args, "baselines", None) or [])]
    verdicts, versus = {}, {}
    for scene, scene_table in rows.items():
        candidates = [row for row in scene_table if row["variant"] != "3DGS" and row["variant"] not in baselines]
        base = next((row for row in scene_table if row["variant"] == "3DGS"), None)
        if base is not None:
            for row in candidates:
                verdicts.setdefault(scene, {})[row["variant"]] = verdict(base, row)
        # each ESGS row against each published baseline, by the same criteria
        for label in baselines:
            other = next((row for row in scene_table if row["variant"] == label), None)
            for row in candidates if other is not None else []:
                versus.setdefault(scene, {}).setdefault(label, {})[row["variant"]] = verdict(other, row)
    sky_rows = aggregate(sky, list(SKY_KEYS), group_by=("variant",)) if sky else []
    result = {"rows": rows, "verdicts": verdicts, "sky": sky_rows, "failed": failed,
              "settings": vars(args) | {"out": str(args.out)}}
    if baselines:
        result["versus_baselines"] = versus
    atomic_write_json(Path(args.out) / "acceptance.json", result)
    if args.doc:
        atomic_write_text(Path(args.doc), markdown(args, scenes, rows, verdicts, sky_rows, failed, started, versus))


def _mark(value) -> str:
    return "n/a" if value is None else ("yes" if value else "**no**")


def _verdict_line(label: str, against: str, result: dict) -> str:
    ratio = result["distance"].get("ratio")
    psnr = result["psnr"]
    change = "n/a" if psnr["change_db"] is None else f"{psnr['change_db']:+.2f} dB" + (
        " (beyond the spread)" if psnr["significant"] else " (within the spread)")
    return (f"- {label} vs {against}: higher SSIM {_mark(result['ssim']['pass'])}; lower LPIPS "
            f"{_mark(result['lpips']['pass'])}; distance >= 20 % lower {_mark(result['distance']['pass'])}"
            f"{'' if ratio is None else f' (ratio {ratio:.2f})'}; PSNR change {change}.")


def markdown(args, scenes, rows, verdicts, sky_rows, failed, started, versus=None) -> str:
    from esgs.core.experiments.acceptance import DISTANCE_RATIO

    lines = ["# ESGS acceptance study (issue #6)", "",
             f"Generated by `benchmarks/esgs_acceptance.py` on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} "
             f"({platform.machine()}, CPU, shared 2-core machine; {time.time() - started:.0f} s in this invocation).", "",
             "## Setup", "",
             f"- Scenes: {', '.join(scenes)}; each rendered with `esgs scene` at {args.resolution}, {args.views} views "
             f"(every 8th view held out: {args.views - len(range(0, args.views, 8))} training views, "
             f"{len(range(0, args.views, 8))} test views).",
             "- **Sparse points are real SfM**: the scene export's `sparse/0` points are exact surface samples lifted "
             "from the rendered depth; this study replaces them (`core/experiments/sfm_scene.py`) by SIFT matches of "
             "the rendered images triangulated with the known poses (pycolmap `triangulate_points`). Both the initial "
             "Gaussians and the `sfm` depth priors come from these points. The `gt` priors are the renderer's exact "
             "depth and normals (upper bound).",
             (f"- Training: **equal training time**, {args.max_minutes:g} min for every run (`--max-minutes`; "
              f"evaluation off the clock), up to {args.iterations} steps on the schedule of {args.iterations} steps, "
              if args.max_minutes else f"- Training: {args.iterations} steps for every run, ")
             + f"at width {args.width or 'full'} px, seeds "
             f"{', '.join(map(str, args.seeds))}, `--threads {args.threads}`, "
             + ("every trainer default (`--train-defaults`: the sky model, `--mask-source auto`)."
                if args.train_defaults else
                "photometric loss on whole images (`mask_source none`), the trainer's defaults otherwise."),
             *([f"- ESGS rows with {', '.join(args.esgs_option)} (`--esgs-option`)."] if args.esgs_option else []),
             "- 3DGS: the trainer's baseline. ESGS: full ESGS as `full_esgs` defines it for the source: depth + normal "
             "prior losses (the ones the source has: `sfm` has depth only) + GPDFN with K = 3, and with `auto` "
             "Gaussians seeded from the depth prior.",
             *([f"- Published baselines (`--baselines`): "
                f"{', '.join(row.label for row in baseline_rows(args.baselines))}, run as published like `esgs bench`'s "
                "rows (constant background, no sky masks, no priors; docs/baselines.md) with the same steps, seeds "
                "and width. Each ESGS row is also compared with each of them by the same criteria."]
               if getattr(args, "baselines", None) else []),
             "- Metrics on the held-out views: SSIM, PSNR, LPIPS (AlexNet, v0.1); distances: Gaussian centres with opacity "
             ">= 0.5 to `mesh/ground_truth.ply` (scene units, metres). Mean ± std over seeds (population std).",
             f"- Verdict: ESGS with each non-gt source against 3DGS on the same scene. A criterion passes when "
             f"the difference of the means exceeds the sum of both standard deviations over seeds; the distance "
             f"must be below {DISTANCE_RATIO:.1f} x 3DGS's mean by more than the spreads.", ""]
    columns = list(QUALITY_COLUMNS) + [("n_gaussians", "Gaussians", 0), ("train_s", "train (s)", 0)]
    if args.max_minutes:
        columns.append(("steps", "steps", 0))  # what each method made of the same minutes
    for scene, table in rows.items():
        lines += [f"## {scene}", "", markdown_table(table, columns)]
        for label, result in verdicts.get(scene, {}).items():
            lines.append(_verdict_line(label, "3DGS", result))
        for against, results in (versus or {}).get(scene, {}).items():
            for label, result in results.items():
                lines.append(_verdict_line(label, against, result))
        lines.append("")
    if sky_rows:
        lines += ["## The sky fix (rover_horizon)", "",
                  "The gt maps encode sky as invalid (depth 0, zero normal), so with gt priors the loss skips sky with or "
                  "without masks: the switch has no effect by construction. A dense predictor fills the sky instead; "
                  "`gt_skyfilled` emulates one (surface exact, sky depth = the view's farthest surface depth, sky "
                  "normal facing the camera, mask = gt). ESGS is trained with it with `use_masks` on (the fix) and off.",
                  "Held-out views: PSNR over all pixels, over sky pixels and over surface pixels; mean rendered alpha "
                  "on sky pixels; median relative depth error of surface pixels within 4 px of the sky (the horizon "
                  "band); mean Gaussian-to-mesh distance.", "",
                  "| method | seeds | PSNR | PSNR sky | PSNR surface | alpha sky | horizon depth err. | dist. mean |",
                  "|---|---|---|---|---|---|---|---|"]
        for row in sky_rows:
            cells = [row["variant"], str(len(row["seeds"]))] + [format_cell(row[key], 3 if key in (
                "alpha_sky", "horizon_depth_error", "distance_mean") else 2) for key in SKY_KEYS]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    if failed:
        lines += ["## Failed runs", ""] + [f"- {item}" for item in failed] + [""]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--preset", action="append", default=[], help="synthetic preset (repeat)")
    parser.add_argument("--scene", action="append", default=[], help="NAME=PATH of an existing scene folder (repeat)")
    parser.add_argument("--sky-preset", default="", help="preset with sky for the sky-fix study (empty = skip)")
    parser.add_argument("--sky-priors", nargs="+", default=[PriorSource.GT_SKYFILLED],
                        help="prior sources of the sky study's ESGS arms (gt_skyfilled emulates a dense predictor; ndn is one)")
    parser.add_argument("--sky-loss-weights", type=float, nargs="*", default=[],
                        help="sky study: also train masks + the sky loss (--sky-weight) at each of these weights")
    parser.add_argument("--sky-ignore-masks", action=argparse.BooleanOptionalAction, default=True,
                        help="sky study: also train with the masks ignored")
    parser.add_argument("--sky-baseline", action=argparse.BooleanOptionalAction, default=True,
                        help="also train 3DGS on the sky scene")
    parser.add_argument("--sources", nargs="+", default=list(SOURCES), help="prior sources of the ESGS rows")
    parser.add_argument("--views", type=int, default=10)
    parser.add_argument("--resolution", default="320x180")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--sky-seeds", type=int, nargs="+", default=None, help="seeds of the sky study (default: --seeds)")
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument("--width", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--max-minutes", type=float, default=0.0,
                        help="equal training time instead of equal steps: every run trains this many minutes "
                             "(evaluation off the clock), --iterations being its step cap and schedule length "
                             "(as esgs bench's budgets: twice the equal-step count for the shortest budget)")
    parser.add_argument("--esgs-option", action="append", default=[], metavar="KEY=VALUE",
                        help="set an ESGSConfig field on every ESGS row, e.g. depth_weight=3 (repeat; use its own --out)")
    parser.add_argument("--train-defaults", action="store_true",
                        help="train with today's defaults (sky model, masks from --mask-source auto) instead of the "
                             "study's historical --mask-source none")
    parser.add_argument("--baselines", nargs="+", default=[], choices=baseline_choices(), metavar="METHOD",
                        help="also train these published baselines on every scene of the main study, as published "
                             f"like esgs bench's rows, with 3DGS's steps and seeds ({', '.join(baseline_choices())})")
    parser.add_argument("--doc", type=Path, default=None)
    parser.add_argument("--report-only", action="store_true", help="rewrite the report from finished runs")
    args = parser.parse_args()
    started = time.time()
    root = args.out / "scenes"
    sources = {preset: root / f"{preset}_{args.views}v_{args.resolution}" for preset in args.preset}
    for preset, path in sources.items():
        make_scene(preset, path, args.views, args.resolution)
    for item in args.scene:
        name, _, path = item.partition("=")
        sources[name] = Path(path)
    scenes = {name: sfm_variant(path, root, name) for name, path in sources.items()}
    for source in ("ndn", "labels", "auto"):
        if source in args.sources:
            for scene in scenes.values():
                ensure_computed_priors(scene, source)
    train = {"width": args.width, "threads": args.threads, "backend": "auto", "lpips": True, "save_renders": False}
    if args.max_minutes:
        train["max_minutes"] = args.max_minutes
    if not args.train_defaults:
        train["mask_source"] = "none"  # the study's historical setting: photometric loss on whole images
    tasks = plan_runs(scenes, args.out, iterations=args.iterations, seeds=args.seeds, train=train,
                      sources=args.sources, esgs_options=esgs_options(args.esgs_option))
    tasks += baseline_tasks(scenes, args.out, iterations=args.iterations, seeds=args.seeds, train=train,
                            names=args.baselines)
    sky = []
    if args.sky_preset:
        sky_scene = sfm_variant(make_scene(args.sky_preset, root / f"{args.sky_preset}_{args.views}v_{args.resolution}",
                                           args.views, args.resolution), root, args.sky_preset)
        if PriorSource.GT_SKYFILLED in args.sky_priors and not SceneDir(sky_scene).prior(PriorSource.GT_SKYFILLED).is_dir():
            write_sky_filled_priors(sky_scene)
        if "ndn" in args.sky_priors:
            ensure_computed_priors(sky_scene, "ndn")
        sky = sky_tasks(sky_scene, args.out, args.iterations, args.sky_seeds or args.seeds, train,
                        baseline=args.sky_baseline, priors=tuple(args.sky_priors),
                        sky_weights=tuple(args.sky_loss_weights), ignore_masks=args.sky_ignore_masks)
    # the sky runs of the first sky seed come after the main runs of the first seed, the
    # other sky seeds after every main run (the main study matters most if time runs out)
    first_sky = sky[0].seed if sky else 0
    last = max(args.seeds)
    ordered = sorted(tasks + sky, key=lambda task: (task.seed, 0) if task.scene_name != "sky" else (
        (task.seed, 1) if task.seed == first_sky else (last, 2 + task.seed)))
    summaries, sky_summaries, failed = [], [], []
    for task in ordered:
        if args.report_only and not task.finished():
            continue
        status = "skipped" if task.finished() else "training"
        print(f"{time.strftime('%H:%M:%S')} {status} {task.name}", flush=True)
        try:
            summary = run_task(task)
            if task.scene_name == "sky":
                sky_summaries.append(with_sky_figures(task, summary))
            else:
                summaries.append(summary)
        except Exception as err:  # noqa: BLE001 - one bad run must not lose the others
            failed.append(f"{task.name}: {type(err).__name__}: {err}")
            print(f"FAILED {failed[-1]}", flush=True)
        report(args, scenes, summaries, sky_summaries, failed, started)
    report(args, scenes, summaries, sky_summaries, failed, started)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
