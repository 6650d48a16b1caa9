"""Sky handling on outdoor scenes: held-out image quality, sky-pixel error and geometry.

Trains each arm on each scene (3DGS, same steps and seed) and writes, per run, the held-out
PSNR / SSIM / LPIPS, the mean absolute colour error on the held-out views' sky pixels
(gt masks), the opaque Gaussians' distance to the true mesh, and the Gaussian count:

- ``none``: ``--sky none --mask-source none``, plain 3DGS (the sky is painted by Gaussians);
- ``envmap``: the default (the sky model, the sky-alpha term on the gt masks);
- ``envmap-alphaW``: the default with ``--sky-alpha-weight W`` (tuning).

Runs from before the sky model (masks dropping the sky from the loss) are measured with
``--measure-run ARM/SCENE=RUN_DIR`` (trained with that code; this script only measures them).
Tuning arms: ``--alpha-weights``, ``--surface-alpha-weights``, ``--sky-degrees``,
``--sky-smooth-weights`` (the sky's Dirichlet-energy prior, ``envmap-smoothW``). The JSON
holds every row, the summary over seeds (with the PSNR of held-out views with and without
sky, 1 % of the image) and the outdoor acceptance per scene; ``--summarize A.json ...``
prints them for finished studies.

    .venv/bin/python benchmarks/sky_study.py --scene tune=SCENE ... --out DIR --iterations 1000 \\
        [--arms none envmap] [--alpha-weights 0 0.2] [--seeds 0] [--json benchmarks/results/sky_study.json]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable

# idle OpenMP threads spin by default and take the cores a busy machine's other runs need
# (docs/rasterizer.md, "Spinning OpenMP workers"); set before torch loads
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from esgs.core.experiments.runs import RunTask, geometry_figures, run_task  # noqa: E402
from esgs.core.formats.run_dir import RunDir  # noqa: E402
from esgs.core.formats.scene_dir import SceneDir  # noqa: E402
from esgs.core.io_utils import atomic_write_json  # noqa: E402


def sky_error(run_dir: Path, scene: Path) -> dict[str, Any]:
    """Mean absolute colour error (0..1) of the held-out views on their sky and surface pixels
    (gt masks: 0 = sky), and PSNR per view."""
    from esgs.core.methods import run_renderer
    from esgs.core.priors.io import load_prior_maps

    renderer = run_renderer(run_dir)
    sky_abs, sky_count, surface_abs, surface_count, views = 0.0, 0, 0.0, 0, []
    for view in renderer.views("test"):
        image = renderer.render(view).image.clamp(0, 1)
        target = view.image_float(renderer.device)
        error = (image - target).abs().mean(dim=-1)
        sky = ~torch.from_numpy(load_prior_maps(scene, "gt", view.name, size=(view.width, view.height)).mask.astype(bool))
        sky_abs += float(error[sky].sum())
        sky_count += int(sky.sum())
        surface_abs += float(error[~sky].sum())
        surface_count += int((~sky).sum())
        mse = float(((image - target) ** 2).mean())
        views.append({"name": view.name, "psnr": -10 * np.log10(max(mse, 1e-12)), "sky_fraction": float(sky.float().mean())})
    return {"sky_mae": sky_abs / sky_count if sky_count else None,
            "surface_mae": surface_abs / surface_count if surface_count else None, "views": views}


def measure(run_dir: Path, scene: Path) -> dict[str, Any]:
    metrics = json.loads(RunDir(run_dir).metrics.read_text())
    mesh = SceneDir(scene).ground_truth_mesh
    result = {"psnr": metrics["psnr"], "ssim": metrics["ssim"], "lpips": metrics.get("lpips"),
              "n_gaussians": metrics.get("n_gaussians"), **sky_error(run_dir, scene)}
    if mesh.is_file():
        result.update(geometry_figures(RunDir(run_dir).point_cloud, mesh))
    return result


SKY_VIEW_FRACTION = 0.01
SUMMARY_KEYS = ("psnr", "ssim", "lpips", "sky_mae", "distance_mean", "n_gaussians", "psnr_sky_views",
                "psnr_ground_views")


def view_groups(row: dict[str, Any]) -> dict[str, Any]:
    """Mean held-out PSNR of the views that show sky (rover-height views) and of those that do not."""
    # 1 % of the image: an aerial view with a few sky pixels at its border is still an aerial view
    sky = [view["psnr"] for view in row.get("views", []) if view["sky_fraction"] >= SKY_VIEW_FRACTION]
    ground = [view["psnr"] for view in row.get("views", []) if view["sky_fraction"] < SKY_VIEW_FRACTION]
    return {"psnr_sky_views": float(np.mean(sky)) if sky else None,
            "psnr_ground_views": float(np.mean(ground)) if ground else None}


def summarize(rows: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, float]]]:
    """{"scene/arm": {figure: {mean, std, n}}} over the seeds of each scene and arm."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(f"{row['scene']}/{row['arm']}", []).append({**row, **view_groups(row)})
    summary = {}
    for name, members in groups.items():
        summary[name] = {}
        for key in SUMMARY_KEYS:
            values = [m[key] for m in members if m.get(key) is not None]
            if values:
                summary[name][key] = {"mean": float(np.mean(values)), "std": float(np.std(values, ddof=1)) if len(values) > 1 else 0.0,
                                      "n": len(values)}
    return summary


def acceptance(rows: list[dict[str, Any]], default: str = "envmap", baseline: str = "none",
               before: str = "before") -> dict[str, dict[str, Any]]:
    """The outdoor-scene acceptance per scene (issue #22), from the seed means of ``rows``:
    aerial (no-sky) views' PSNR at least the baseline's, sky views' at least +3 dB over it,
    SSIM and LPIPS no worse, sky MAE <= 0.05, and the opaque Gaussians no farther from the mesh
    than the ``before`` arm's (the code that dropped masked pixels), when that arm was measured."""
    summary = summarize(rows)
    verdicts = {}
    for scene in sorted({row["scene"] for row in rows}):
        ours, theirs = summary.get(f"{scene}/{default}"), summary.get(f"{scene}/{baseline}")
        if not ours or not theirs:
            continue
        mean = lambda table, key: table[key]["mean"] if key in table else None  # noqa: E731
        checks: dict[str, Any] = {}

        def check(name: str, a: Any, b: Any, better: Callable[[float, float], bool]) -> None:
            if a is not None and b is not None:  # a figure missing on either side is not checked
                checks[name] = bool(better(a, b))

        check("ground_views_psnr", mean(ours, "psnr_ground_views"), mean(theirs, "psnr_ground_views"),
              lambda a, b: a >= b)
        check("sky_views_psnr_plus_3db", mean(ours, "psnr_sky_views"), mean(theirs, "psnr_sky_views"),
              lambda a, b: a >= b + 3.0)
        check("ssim", mean(ours, "ssim"), mean(theirs, "ssim"), lambda a, b: a >= b)
        check("lpips", mean(ours, "lpips"), mean(theirs, "lpips"), lambda a, b: a <= b)
        check("sky_mae_below_0.05", mean(ours, "sky_mae"), 0.05, lambda a, b: a <= b)
        earlier = summary.get(f"{scene}/{before}")
        if earlier:
            check("distance_not_above_before", mean(ours, "distance_mean"), mean(earlier, "distance_mean"),
                  lambda a, b: a <= b)
        verdicts[scene] = {"checks": checks, "met": all(checks.values())}
    return verdicts


def arms(names: list[str], alpha_weights: list[float], surface_weights: list[float] = (),
         sky_degrees: list[int] = (), smooth_weights: list[float] = ()) -> dict[str, dict[str, Any]]:
    from esgs.core.train.config import VANILLA_3DGS

    table = {"none": dict(VANILLA_3DGS), "envmap": {}}
    chosen = {name: table[name] for name in names}
    for weight in alpha_weights:
        chosen[f"envmap-alpha{weight:g}"] = {"sky_alpha_weight": weight}
    for weight in surface_weights:
        chosen[f"envmap-surface{weight:g}"] = {"surface_alpha_weight": weight}
    for degree in sky_degrees:
        chosen[f"envmap-degree{degree}"] = {"sky_degree": degree}
    for weight in smooth_weights:
        chosen[f"envmap-smooth{weight:g}"] = {"sky_smooth_weight": weight}
    return chosen


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", action="append", default=[], help="NAME=SCENE_DIR (repeat)")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--iterations", type=int, default=1000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--arms", nargs="*", default=["none", "envmap"])
    parser.add_argument("--alpha-weights", type=float, nargs="*", default=[])
    parser.add_argument("--surface-alpha-weights", type=float, nargs="*", default=[])
    parser.add_argument("--sky-degrees", type=int, nargs="*", default=[])
    parser.add_argument("--sky-smooth-weights", type=float, nargs="*", default=[])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--measure-run", action="append", default=[], help="ARM/SCENE=RUN_DIR of an older run")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--summarize", type=Path, nargs="+", default=None,
                        help="print the summary of these study JSON files (rows merged) and exit")
    args = parser.parse_args(argv)
    if args.summarize:
        rows = [row for path in args.summarize for row in json.loads(path.read_text())["rows"]]
        for name, figures in summarize(rows).items():
            print(name, {key: f"{value['mean']:.4g} ± {value['std']:.2g} (n={value['n']})" for key, value in figures.items()})
        for scene, verdict in acceptance(rows).items():
            print(f"acceptance {scene}: {'met' if verdict['met'] else 'NOT met'} {verdict['checks']}")
        return 0
    if not args.scene or args.out is None:
        parser.error("--scene and --out are required (unless --summarize)")
    scenes = dict(item.split("=", 1) for item in args.scene)
    rows = []
    for seed in args.seeds:
        for scene_name, scene in scenes.items():
            for arm, settings in arms(args.arms, args.alpha_weights, args.surface_alpha_weights, args.sky_degrees,
                                        args.sky_smooth_weights).items():
                out = args.out / scene_name / arm / f"seed{seed}"
                config = {"iterations": args.iterations, "seed": seed, "threads": args.threads, "lpips": True,
                          "save_renders": True, "checkpoint_every": 0, **settings}
                started = time.perf_counter()
                run_task(RunTask(name=f"{scene_name}/{arm}/seed{seed}", scene=Path(scene), out=out, config=config,
                                 variant=arm, seed=seed, scene_name=scene_name, measure_render=False))
                row = {"scene": scene_name, "arm": arm, "seed": seed, "settings": settings,
                       "wall_s": time.perf_counter() - started, **measure(out, Path(scene))}
                rows.append(row)
                print(json.dumps({k: v for k, v in row.items() if k != "views"}), flush=True)
    for item in args.measure_run:
        label, run = item.split("=", 1)
        arm, scene_name = label.split("/", 1)
        rows.append({"scene": scene_name, "arm": arm, "seed": None, "run": run,
                     **measure(Path(run), Path(scenes[scene_name]))})
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "views"}), flush=True)
    if args.json is not None:
        atomic_write_json(args.json, {"command": " ".join(sys.argv), "iterations": args.iterations,
                                      "scenes": scenes, "rows": rows, "summary_over_seeds": summarize(rows),
                                      "acceptance": acceptance(rows)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
