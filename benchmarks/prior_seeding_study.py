"""Gaussians seeded from the depth prior (``prior_points``): full ESGS with each count against
full ESGS without, and plain ``esgs train`` (3DGS + sky model) as the reference, equal steps.

``--black`` adds the rows as shipped before 2026-12-07, when the sky model started from
black (``sky_init black``) and nothing was seeded. Every scene x seed x row runs once, one after another, cached in
``OUT/runs/<scene>/<row>/seed<s>`` (a finished run is not repeated). Rows: ``3dgs_sky``
(plain ``esgs train``) and ``esgs_p<N>`` (``full_esgs(priors)`` with ``prior_points=N``;
N = 0 is full ESGS as shipped before seeding). After every run ``OUT/seeding.json`` is
rewritten; ``--json`` copies it where the docs quote it from. Each row's figures are the mean
and standard deviation over the runs, and its paired differences against ``esgs_p0``,
``esgs_p0_black`` and ``3dgs_sky`` on the same scene and seed (held-out SSIM / PSNR / LPIPS, mean distance of the opaque Gaussians to the
scene's true mesh as a ratio, training seconds as a ratio, Gaussians at the end).

    .venv/bin/python benchmarks/prior_seeding_study.py SCENE [SCENE ...] --out DIR [--points 0 1000]
        [--seeds 0 1 2] [--iterations 500] [--priors auto] [--threads 2] [--black] [--json FILE]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

# idle OpenMP threads spin by default and take the cores a busy machine's other runs need
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from esgs.core.config import config_to_dict  # noqa: E402
from esgs.core.experiments.runs import RunTask, run_task  # noqa: E402
from esgs.core.formats.scene_dir import SceneDir  # noqa: E402
from esgs.core.io_utils import atomic_write_json  # noqa: E402
from esgs.core.methods import full_esgs  # noqa: E402

FIGURES = ("ssim", "psnr", "lpips", "distance_mean", "train_s", "n_gaussians")
#: paired figures: differences for these, ratios for the rest of FIGURES
DIFFERENCES = ("ssim", "psnr", "lpips", "n_gaussians")


def tasks_for(scene: Path, out: Path, *, points: list[int], seeds: list[int], iterations: int, priors: str,
              threads: int, baseline: bool, black: bool = False) -> list[RunTask]:
    """``black``: also the rows as shipped before 2026-12-07 (sky model from black, no seeding):
    ``3dgs_sky_black`` and ``esgs_p0_black``."""
    mesh = SceneDir(scene).ground_truth_mesh
    train = {"iterations": iterations, "threads": threads, "backend": "cpu"}
    esgs = {n: config_to_dict(full_esgs(priors, scene=scene, prior_points=n)) for n in points}
    rows = [("3dgs_sky_black", "3dgs", None, {"sky_init": "black"})] if baseline and black else []
    rows += [("3dgs_sky", "3dgs", None, {})] if baseline else []
    rows += [("esgs_p0_black", "esgs", esgs[0], {"sky_init": "black"})] if black else []
    rows += [(f"esgs_p{n}", "esgs", esgs[n], {}) for n in points]
    tasks = []
    for seed in seeds:
        for key, method, method_config, settings in rows:
            tasks.append(RunTask(name=f"{scene.name}/{key}/seed{seed}", scene=scene,
                                 out=out / "runs" / scene.name / key / f"seed{seed}",
                                 config={**train, **settings, "seed": seed, "method": method,
                                         "method_config": method_config},
                                 variant=key, seed=seed, scene_name=scene.name,
                                 mesh=mesh if mesh.is_file() else None, measure_render=False))
    return tasks


def _stats(values: list[float]) -> dict:
    values = [v for v in values if v is not None]
    if not values:
        return {"mean": None, "std": None, "n": 0}
    return {"mean": statistics.fmean(values), "std": statistics.stdev(values) if len(values) > 1 else 0.0,
            "n": len(values)}


#: the rows every other row is paired with, where present
REFERENCES = ("esgs_p0", "esgs_p0_black", "3dgs_sky")


def _paired(summaries: list[dict], runs: list[dict], reference: str) -> dict:
    paired: dict[str, list] = {figure: [] for figure in FIGURES}
    for run in runs:
        base = next((s for s in summaries if s["variant"] == reference and s["scene"] == run["scene"]
                     and s["seed"] == run["seed"]), None)
        if base is None:
            continue
        for figure in FIGURES:
            a, b = run.get(figure), base.get(figure)
            if a is not None and b is not None and (figure in DIFFERENCES or b):
                paired[figure].append(a - b if figure in DIFFERENCES else a / b)
    return {figure: _stats(values) for figure, values in paired.items() if values}


def summarise(summaries: list[dict]) -> dict:
    """Per row: mean and std of every figure, and paired against each reference row on the
    same scene and seed (differences for SSIM, PSNR, LPIPS and the count, ratios otherwise)."""
    rows: dict[str, dict] = {}
    variants = {s["variant"] for s in summaries}
    for key in sorted(variants):
        runs = [s for s in summaries if s["variant"] == key]
        row = {figure: _stats([r.get(figure) for r in runs]) for figure in FIGURES}
        for reference in REFERENCES:
            if reference in variants and reference != key:
                row[f"paired_vs_{reference}"] = _paired(summaries, runs, reference)
        rows[key] = row
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", type=Path, nargs="+")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--points", type=int, nargs="+", default=[0, 1000], help="prior_points of the ESGS rows")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--iterations", type=int, default=500)
    parser.add_argument("--priors", default="auto")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-baseline", dest="baseline", action="store_false", help="leave out the 3dgs_sky row")
    parser.add_argument("--black", action="store_true",
                        help="also the rows as shipped before 2026-12-07: 3dgs_sky_black and esgs_p0_black "
                             "(sky model from black, no seeding)")
    parser.add_argument("--json", type=Path, default=None, help="also write the summary here")
    args = parser.parse_args(argv)
    if 0 not in args.points:
        parser.error("--points must include 0 (full ESGS without seeding: the paired reference)")
    tasks = [task for scene in args.scenes
             for task in tasks_for(scene.resolve(), args.out, points=args.points, seeds=args.seeds,
                                   iterations=args.iterations, priors=args.priors, threads=args.threads,
                                   baseline=args.baseline, black=args.black)]
    summaries = []
    command = "python benchmarks/prior_seeding_study.py " + " ".join(sys.argv[1:] if argv is None else argv)
    for index, task in enumerate(tasks, 1):
        started = time.perf_counter()
        summary = run_task(task)
        summaries.append(summary)
        print(f"[{index}/{len(tasks)}] {task.name}: PSNR {summary['psnr']:.2f} SSIM {summary['ssim']:.4f} "
              f"LPIPS {summary['lpips']:.4f} dist {summary['distance_mean']} Gaussians {summary['n_gaussians']} "
              f"train {summary['train_s']:.0f} s ({time.perf_counter() - started:.0f} s)", flush=True)
        report = {"command": command, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                  "iterations": args.iterations, "priors": args.priors, "threads": args.threads,
                  "scenes": [str(s) for s in args.scenes], "seeds": args.seeds, "points": args.points,
                  "rows": summarise(summaries), "runs": summaries}
        atomic_write_json(args.out / "seeding.json", report)
        if args.json is not None:
            atomic_write_json(args.json, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
