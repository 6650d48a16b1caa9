"""Training speed and quality at fixed wall-clock budgets (prints figures; not a test).

Usage::

    python benchmarks/bench_train.py --scene SCENE [--width 480] [--iterations 7000]
        [--budgets 60 300 900] [--backend auto] [--threads 0] [--lpips]

SCENE is any COLMAP scene folder (images/ + sparse/0). To make a synthetic one of ~30
views at 480x270 (needs the bpy module; Cycles on the CPU, a few minutes)::

    esgs scene --preset cratered_plain --views 30 --resolution 480x270 --out /tmp/bench_scene

Prints: seconds per step over the first and the last 50 steps before each budget,
Gaussian count, peak resident memory, and test PSNR/SSIM/LPIPS whenever the training time
(evaluation excluded) crosses a budget. The machine's load average is printed at the
start and the end: on a shared machine the figures are only comparable at similar load.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, required=True, help="COLMAP scene folder")
    parser.add_argument("--out", type=Path, default=None, help="run folder (default: a temporary one)")
    parser.add_argument("--width", type=int, default=480, help="training image width in pixels")
    parser.add_argument("--iterations", type=int, default=7000, help="schedule length (densification scales with it)")
    parser.add_argument("--budgets", type=float, nargs="+", default=[60.0, 300.0, 900.0],
                        help="training seconds at which to evaluate")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "reference", "cuda"))
    parser.add_argument("--threads", type=int, default=0)
    parser.add_argument("--lpips", action="store_true", help="also LPIPS (needs cached weights)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    import torch

    from esgs.core.train import TrainConfig
    from esgs.core.train.evaluate import evaluate_model
    from esgs.core.train.trainer import Trainer

    out = args.out or Path(tempfile.mkdtemp(prefix="bench_train_")) / "run"
    config = TrainConfig(scene=args.scene, out=out, width=args.width, iterations=args.iterations, backend=args.backend,
                         threads=args.threads, seed=args.seed, lpips=args.lpips, checkpoint_every=0)
    print(f"load average at start: {os.getloadavg()} on {os.cpu_count()} CPUs", flush=True)
    started = time.monotonic()
    trainer = Trainer(config)
    trainer._start_run_dir(None)
    trainer.setup()
    view = trainer.data.train[0]
    print(f"scene {args.scene}: {len(trainer.data.train)} train / {len(trainer.data.test)} test views at "
          f"{view.width}x{view.height}, {len(trainer.gaussians)} initial Gaussians, backend {trainer.backend}, "
          f"torch threads {torch.get_num_threads()}, setup {time.monotonic() - started:.1f} s", flush=True)

    budgets = sorted(args.budgets)
    training_s = 0.0
    step_times: list[float] = []
    step = 0
    print(f"{'budget_s':>8} {'step':>6} {'s/step first50':>14} {'s/step last50':>13} {'gaussians':>9} "
          f"{'rss_MiB':>8} {'psnr':>7} {'ssim':>6} {'lpips':>6}", flush=True)
    for budget in budgets:
        while training_s < budget and step < args.iterations:
            step += 1
            tick = time.monotonic()
            trainer.train_step(step)
            elapsed = time.monotonic() - tick
            step_times.append(elapsed)
            training_s += elapsed
        sh_degree = trainer.schedule.sh_degree_at(step, config.sh_degree)
        metrics = evaluate_model(trainer.gaussians, trainer.data, backend=trainer.backend,
                                 background=trainer.background, sh_degree=sh_degree, use_lpips=args.lpips,
                                 num_threads=trainer.num_threads)
        first = sum(step_times[:50]) / max(len(step_times[:50]), 1)
        last = sum(step_times[-50:]) / max(len(step_times[-50:]), 1)
        lpips = "n/a" if metrics["lpips"] is None else f"{metrics['lpips']:.4f}"
        print(f"{budget:8.0f} {step:6d} {first:14.3f} {last:13.3f} {len(trainer.gaussians):9d} {_peak_rss_mib():8.0f} "
              f"{metrics['psnr']:7.2f} {metrics['ssim']:6.4f} {lpips:>6}", flush=True)
        if step >= args.iterations:
            break
    print(f"load average at end: {os.getloadavg()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
