"""What one training step costs, part by part: plain 3DGS against ESGS with its parts added one at a time.

Every arm trains the same scene from the same N Gaussians (drawn from the scene's SfM points,
isotropic scales from their 3 nearest neighbours, opacity 0.5), past densification (steps from
20,001 of the 30,000-step reference schedule: SH degree 3, every prior term on, no
densification or opacity reset), so the Gaussian count stays N and only the method differs.
The cost of a part is the difference of the mean step times of two arms (its forward and
backward together). ``--profile`` adds a cProfile of the full-ESGS arm's steps, grouped by
the functions that own the time. Prints a table; ``--json`` writes the figures.

    python benchmarks/profile_step.py SCENE --gaussians 100000 --width 480 --threads 2 \\
        --priors gt --steps 20 --repeats 3 --json benchmarks/results/step_profile.json --profile

Speed is measured here, never asserted in tests. Run it on an otherwise idle machine: the
load average at the start and the end is recorded.
"""
from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

FIRST_STEP = 20_001  # of the 30,000-step reference schedule: after densification, every term on


def arms(priors: str) -> dict[str, dict[str, Any]]:
    """TrainConfig overrides per arm: 3DGS as users get it, then ESGS part by part."""
    from dataclasses import asdict

    from esgs.core.methods import full_esgs

    full = full_esgs(priors)

    def esgs(**changes: Any) -> dict[str, Any]:
        return {"method": "esgs", "method_config": asdict(replace(full, **changes))}

    return {
        "3dgs": {},
        "depth": esgs(normal=False, consistency=False, gpdfn=False),
        "depth+normal": esgs(gpdfn=False),
        "gpdfn": esgs(depth=False, normal=False, consistency=False, sky_weight=0.0),
        "full esgs": esgs(),
        "full esgs, GPDFN every 4": esgs(gpdfn_every=4),
        "full esgs, GPDFN width 16 (before 2026-11-29)": esgs(gpdfn_hidden=16),
    }


# parts of a step: (function names, the file they must be in); cumulative cProfile time of the
# outermost calls. The backward of the rasterizer and of GPDFN's fusion core run inside
# autograd's backward, so they are also part of the "backward" line (shown apart as well).
PROFILE_GROUPS: dict[str, tuple[tuple[str, ...], str]] = {
    "rasterizer forward (projection, SH colours, compositing)": (("rasterization",), "render/api.py"),
    "rasterizer compositing backward (Numba)": (("composite_backward",), "render/"),
    "rasterizer projection backward (Numba)": (("project_backward", "projection_backward"), "render/"),
    "photometric loss (L1 + D-SSIM) forward": (("l1_loss", "dssim_loss"), "train/losses.py"),
    "sky model image": (("image",), "train/sky.py"),
    "prior losses forward (depth, normal, sky, edge weights)": (
        ("_depth_term", "_normal_term", "_sky_term", "_consistency_term"), "prior_hook.py"),
    "GPDFN forward (all)": (("gpdfn_residuals",), "esgs/"),
    "GPDFN voxel table and lookups": (("voxel_table", "sample_voxels"), "esgs/gpdfn.py"),
    "GPDFN fusion core backward (hand-written)": (("backward",), "esgs/gpdfn.py"),
    "backward (all of autograd)": (("backward",), "torch/_tensor.py"),
    "optimizer step": (("step",), "train/optim.py"),
}


def _gaussians(trainer: Any, count: int, seed: int) -> Any:
    from esgs.core.train.gaussians import GaussianModel

    rng = np.random.default_rng(seed)
    points, colours = trainer.data.points_xyz, trainer.data.points_rgb
    if len(points) == 0:
        raise SystemExit("the scene has no SfM points to draw Gaussians from")
    index = rng.choice(len(points), count, replace=count > len(points))
    xyz = points[index].astype(np.float64)
    if count > len(points):  # repeated points: spread them by a fraction of the scene so none coincide
        xyz = xyz + rng.normal(0.0, 1e-3 * float(trainer.data.extent), xyz.shape)
    model = GaussianModel.from_points(xyz, colours[index], max_sh_degree=trainer.config.sh_degree, init_opacity=0.5)
    return model


def time_arm(scene: Path, overrides: dict[str, Any], *, gaussians: int, width: int, threads: int, steps: int,
             warmup: int, seed: int, profile: bool, backend: str = "cpu", ops: int = 0) -> dict[str, Any]:
    import torch

    from esgs.core.config import config_from_dict
    from esgs.core.methods import get_method
    from esgs.core.train.config import TrainConfig
    from esgs.core.train.trainer import Trainer

    with tempfile.TemporaryDirectory(prefix="esgs_profile_") as out:
        config = config_from_dict(TrainConfig, {
            "scene": str(scene), "out": out, "iterations": 30_000, "width": width, "threads": threads,
            "seed": seed, "checkpoint_every": 0, "backend": backend, **overrides})
        trainer = Trainer(config, method=get_method(config.method))
        trainer._initial_gaussians = lambda: _gaussians(trainer, gaussians, seed)  # noqa: SLF001 (a benchmark)
        trainer.setup()
        count = len(trainer.gaussians)
        on_gpu = trainer.device.type == "cuda"
        # GPU work is asynchronous: a step's time is taken once its kernels have finished
        synchronize = torch.cuda.synchronize if on_gpu else (lambda: None)
        if on_gpu:
            torch.cuda.reset_peak_memory_stats()
        times = []
        profiler = cProfile.Profile() if profile else None
        op_profiler = None
        for index in range(warmup + steps):
            if ops and index == warmup:
                op_profiler = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU])
                op_profiler.__enter__()
            started = time.perf_counter()
            if profiler is not None and index >= warmup:
                profiler.enable()
            trainer.train_step(FIRST_STEP + index)
            synchronize()
            if profiler is not None and index >= warmup:
                profiler.disable()
            times.append(time.perf_counter() - started)
        if op_profiler is not None:
            op_profiler.__exit__(None, None, None)
        if len(trainer.gaussians) != count:
            raise SystemExit(f"the Gaussian count changed during timing ({count} -> {len(trainer.gaussians)})")
        timed = times[warmup:]
        result = {"gaussians": count, "mean_s": statistics.fmean(timed), "median_s": statistics.median(timed),
                  "min_s": min(timed),
                  "max_s": max(timed), "steps": len(timed), "torch_threads": torch.get_num_threads(),
                  "loss_terms": [term.name for term in trainer.loss_terms], "backend": backend}
        if on_gpu:
            result["peak_gpu_mib"] = torch.cuda.max_memory_allocated() / 2**20
            result["gpu"] = torch.cuda.get_device_name()
        if profiler is not None:
            result["profile"] = _grouped(profiler, len(timed))
        if op_profiler is not None:
            result["ops"] = _op_table(op_profiler, len(timed))
        return result


def _op_table(profiler: Any, steps: int) -> dict[str, dict[str, float]]:
    """Self CPU milliseconds per step and calls per step of every torch operator (and autograd
    node: a custom Function's backward, Numba kernels included, is its node's self time)."""
    table = {}
    for event in profiler.key_averages():
        table[event.key] = {"self_ms": event.self_cpu_time_total / 1e3 / steps, "calls": event.count / steps}
    return dict(sorted(table.items(), key=lambda item: -item[1]["self_ms"]))


def _grouped(profiler: cProfile.Profile, steps: int) -> dict[str, float]:
    """Seconds per step of each part of :data:`PROFILE_GROUPS`."""
    stats = pstats.Stats(profiler)
    totals: dict[str, float] = {}
    for group, (names, where) in PROFILE_GROUPS.items():
        seconds = 0.0
        for (filename, _line, function), (_cc, _nc, _tt, cumulative, callers) in stats.stats.items():
            if function not in names or where not in filename.replace(os.sep, "/"):
                continue
            # only the outermost calls (a recursive or nested call of the same part is inside them)
            if any(caller[2] in names and where in caller[0].replace(os.sep, "/") for caller in callers):
                continue
            seconds += cumulative
        totals[group] = seconds / steps
    return totals


def _compare_ops(args: Any, chosen: dict[str, Any], names: list[str], rows: dict[str, Any],
                 options: dict[str, Any]) -> None:
    """Op-level profiles of the 3DGS and full-ESGS arms; prints where ESGS's extra time goes."""
    tables = {}
    for name in [n for n in ("3dgs", "full esgs") if n in names]:
        profiled = time_arm(args.scene, chosen[name], profile=False, ops=args.ops, **options)
        tables[name] = profiled["ops"]
        rows[name]["ops"] = profiled["ops"]
        rows[name]["ops_profiled_mean_s"] = profiled["mean_s"]
        total = sum(op["self_ms"] for op in profiled["ops"].values())
        print(f"{name} under torch.profiler: {profiled['mean_s'] * 1e3:.1f} ms/step, {total:.1f} ms of operator self time")
    if len(tables) < 2:
        return
    base, full = tables["3dgs"], tables["full esgs"]
    keys = set(base) | set(full)
    extra = {key: full.get(key, {}).get("self_ms", 0.0) - base.get(key, {}).get("self_ms", 0.0) for key in keys}
    print("operators whose self time full ESGS adds most (ms per step; calls per step in ESGS):")
    for key in sorted(keys, key=lambda k: -extra[k])[:args.ops]:
        print(f"    {key[:70]:70s} {extra[key]:+8.2f}  ({full.get(key, {}).get('calls', 0):.0f} calls)")
    print(f"    total difference: {sum(extra.values()):+.1f} ms")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("--gaussians", type=int, default=100_000)
    parser.add_argument("--width", type=int, default=480, help="training width (the scene's images are resized)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--priors", default="gt", help="prior source of the ESGS arms (cost is the same for every "
                                                          "source; auto adds a confidence map)")
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3, help="times every arm is timed, arms taking turns")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--arms", nargs="+", default=None, help="subset of arms (default: all)")
    parser.add_argument("--backend", default="cpu", choices=("cpu", "cuda"),
                        help="rasterizer backend (cuda: gsplat on the GPU; steps are timed after a synchronize)")
    parser.add_argument("--profile", action="store_true", help="cProfile the full-ESGS and 3DGS arms, grouped")
    parser.add_argument("--ops", type=int, default=0, metavar="N",
                        help="also profile the 3DGS and full-ESGS arms op by op (torch.profiler) and print the N "
                             "operators whose self time differs most between them")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)

    chosen = arms(args.priors)
    names = args.arms or list(chosen)
    load_start = os.getloadavg()
    rows: dict[str, Any] = {}
    options = dict(gaussians=args.gaussians, width=args.width, threads=args.threads, steps=args.steps,
                   warmup=args.warmup, seed=args.seed, backend=args.backend)
    # timed without the profiler (its overhead is not the same for every arm); the arms take
    # turns over the repeats, so a change of the machine's load touches every arm alike
    for repeat in range(args.repeats):
        for name in names:
            timed = time_arm(args.scene, chosen[name], profile=False, **options)
            row = rows.setdefault(name, {"gaussians": timed["gaussians"], "loss_terms": timed["loss_terms"],
                                         "torch_threads": timed["torch_threads"], "repeats": []})
            if "peak_gpu_mib" in timed:
                row["peak_gpu_mib"] = max(row.get("peak_gpu_mib", 0.0), timed["peak_gpu_mib"])
                row["gpu"] = timed["gpu"]
            row["repeats"].append({key: timed[key] for key in ("mean_s", "median_s", "min_s", "max_s", "steps")})
            print(f"[{repeat + 1}/{args.repeats}] {name:26s} mean {timed['mean_s'] * 1e3:7.1f} ms/step "
                  f"(median {timed['median_s'] * 1e3:.1f}, min {timed['min_s'] * 1e3:.1f})", flush=True)
    for name, row in rows.items():
        means = [r["mean_s"] for r in row["repeats"]]
        row.update(mean_s=statistics.fmean(means), spread_s=[min(means), max(means)])
    base = rows["3dgs"]["mean_s"] if "3dgs" in rows else None
    print(f"\nmean of {args.repeats} repeats x {args.steps} steps, {args.gaussians:,} Gaussians, width {args.width}, "
          f"{args.threads} threads:")
    for name, row in rows.items():
        if base:
            row["ratio_to_3dgs"] = row["mean_s"] / base
        ratio = f"  {row['mean_s'] / base:.2f}x 3DGS" if base else ""
        print(f"  {name:26s} {row['mean_s'] * 1e3:7.1f} ms/step (repeats {row['spread_s'][0] * 1e3:.1f}-"
              f"{row['spread_s'][1] * 1e3:.1f}){ratio}")
    for name in [n for n in ("3dgs", "full esgs") if args.profile and n in names]:
        profiled = time_arm(args.scene, chosen[name], profile=True, **options)
        rows[name]["profile"] = profiled["profile"]
        rows[name]["profiled_mean_s"] = profiled["mean_s"]
        print(f"{name} under cProfile ({profiled['mean_s'] * 1e3:.1f} ms/step with its overhead), per step:")
        for group, seconds in profiled["profile"].items():
            print(f"    {group:62s} {seconds * 1e3:8.1f} ms")
    if args.ops:
        _compare_ops(args, chosen, names, rows, options)
    result = {"command": "python " + " ".join([sys.argv[0], *(argv if argv is not None else sys.argv[1:])]),
              "scene": str(args.scene), "width": args.width, "threads": args.threads, "priors": args.priors,
              "backend": args.backend,
              "first_step": FIRST_STEP, "load_average_start": load_start, "load_average_end": os.getloadavg(),
              "arms": rows}
    if args.json:
        from esgs.core.io_utils import atomic_write_json

        atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
