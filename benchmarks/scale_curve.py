"""Seconds per step and peak memory of a 3DGS step against Gaussian count and image size.

Each (count, width) point runs in its own process (peak RSS only grows within a process):
the scene's training views loaded at that width, N Gaussians drawn from its SfM points
(``profile_step.py``'s rule), steps timed past densification. Peak RSS is reported above the
floor of a process that imported torch and the engine and did nothing else, and per Gaussian
above the same floor; the parameters, their Adam moments and gradients are 4 x 59 floats
(~0.92 KiB) per Gaussian at SH degree 3.

    python benchmarks/scale_curve.py SCENE --gaussians 10000 100000 300000 1000000 \\
        --widths 480 960 1920 --threads 2 --steps 6 --json benchmarks/results/scale_curve.json

SCENE's images must be at least as wide as the largest width (they are resized down).
``python benchmarks/scale_curve.py --plot OUT.png RESULT.json ...`` draws the figures (matplotlib).
Speed and memory are measured here, never asserted in tests.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
from pathlib import Path
from typing import Any

PARAMETER_BYTES = 4 * 59 * 4  # parameters + two Adam moments + gradients, float32, SH degree 3


def _child_floor() -> None:
    import torch  # noqa: F401

    import esgs.core.train.trainer  # noqa: F401

    print(json.dumps({"peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}))


def _child_point(scene: str, gaussians: int, width: int, threads: int, steps: int, warmup: int,
                 backend: str = "cpu") -> None:
    sys.path.insert(0, str(Path(__file__).parent))
    from profile_step import time_arm

    timed = time_arm(Path(scene), {}, gaussians=gaussians, width=width, threads=threads, steps=steps,
                     warmup=warmup, seed=0, profile=False, backend=backend)
    point = {"mean_s": timed["mean_s"], "min_s": timed["min_s"], "gaussians": timed["gaussians"],
             "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    if "peak_gpu_mib" in timed:  # the cuda backend: the GPU's peak allocation is the figure that limits a run
        point.update(peak_gpu_mib=timed["peak_gpu_mib"], gpu=timed["gpu"])
    print(json.dumps(point))


def _run_child(arguments: list[str]) -> dict[str, Any]:
    completed = subprocess.run([sys.executable, __file__, *arguments], capture_output=True, text=True)
    if completed.returncode != 0:
        return {"error": (completed.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(completed.stdout.strip().splitlines()[-1])


def plot(results: list[Path], out: Path) -> None:
    """Seconds per step and peak RSS against Gaussian count, one line per (file, width)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (speed, memory) = plt.subplots(1, 2, figsize=(10, 4))
    for path in results:
        data = json.loads(path.read_text())
        for width in sorted({p["width"] for p in data["points"] if "mean_s" in p}):
            points = sorted((p for p in data["points"] if p.get("width") == width and "mean_s" in p),
                            key=lambda p: p["requested_gaussians"])
            counts = [p["requested_gaussians"] for p in points]
            label = f"width {width} ({path.stem})"
            speed.plot(counts, [p["mean_s"] for p in points], marker="o", label=label)
            memory.plot(counts, [p["peak_rss_mib"] for p in points], marker="o", label=label)
    for axis, title, unit in ((speed, "time per 3DGS step (2 threads)", "seconds"),
                              (memory, "peak resident memory", "MiB")):
        axis.set_xscale("log")
        axis.set_xlabel("Gaussians")
        axis.set_ylabel(unit)
        axis.set_title(title)
        axis.grid(True, alpha=0.3)
    memory.axhline(2.5e9 / 2**20, color="grey", linestyle="--", label="2.5 GB")
    memory.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(out, dpi=110)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--plot"]:  # --plot OUT.png RESULT.json ...
        plot([Path(p) for p in argv[2:]], Path(argv[1]))
        return 0
    if argv[:1] == ["--child-floor"]:
        _child_floor()
        return 0
    if argv[:1] == ["--child-point"]:
        scene, gaussians, width, threads, steps, warmup, backend = argv[1:8]
        _child_point(scene, int(gaussians), int(width), int(threads), int(steps), int(warmup), backend)
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("--gaussians", type=int, nargs="+", default=[10_000, 100_000, 300_000, 1_000_000])
    parser.add_argument("--widths", type=int, nargs="+", default=[480, 960, 1920])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--backend", default="cpu", choices=("cpu", "cuda"),
                        help="rasterizer backend (cuda also reports the GPU's peak allocation)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)

    floor = _run_child(["--child-floor"])
    print(f"floor (python + torch + engine imported): {floor.get('peak_rss_mib', float('nan')):.0f} MiB", flush=True)
    points = []
    for width in args.widths:
        for gaussians in args.gaussians:
            point = _run_child(["--child-point", str(args.scene), str(gaussians), str(width), str(args.threads),
                                str(args.steps), str(args.warmup), args.backend])
            point.update(width=width, requested_gaussians=gaussians)
            if "peak_rss_mib" in point and "peak_rss_mib" in floor:
                above = point["peak_rss_mib"] - floor["peak_rss_mib"]
                point["above_floor_mib"] = above
                point["bytes_per_gaussian_above_floor"] = above * 2**20 / gaussians
            points.append(point)
            if "error" in point:
                print(f"width {width:5d}, {gaussians:>9,} Gaussians: failed: {point['error']}", flush=True)
            else:
                print(f"width {width:5d}, {gaussians:>9,} Gaussians: {point['mean_s'] * 1e3:8.1f} ms/step, peak RSS "
                      f"{point['peak_rss_mib']:7.0f} MiB ({point['above_floor_mib']:6.0f} above the floor, "
                      f"{point['bytes_per_gaussian_above_floor']:6.0f} B per Gaussian)"
                      + (f", GPU peak {point['peak_gpu_mib']:.0f} MiB" if "peak_gpu_mib" in point else ""), flush=True)
    result = {"command": "python " + " ".join([sys.argv[0], *argv]), "scene": str(args.scene),
              "threads": args.threads, "backend": args.backend, "steps": args.steps, "warmup": args.warmup, "floor": floor,
              "parameter_bytes_per_gaussian": PARAMETER_BYTES, "load_average_end": os.getloadavg(),
              "points": points}
    if args.json:
        from esgs.core.io_utils import atomic_write_json

        atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
