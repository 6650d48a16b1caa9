"""A full-ESGS training step with each of GPDFN's CPU code paths, side by side in one process.

GPDFN has two pieces that run as Numba kernels on the CPU and as torch statements elsewhere:
the per-Gaussian sampling (features, offset head, voxel reads, kernel weights, own first layer;
``gpdfn._sampling_kernels_apply``) and the fusion core (``gpdfn._fusion_kernels_apply``). This
trains one full-ESGS run (the ``full esgs`` arm of ``profile_step.py``: same scene, N Gaussians
from the SfM points, steps from 20,001 of the reference schedule, no densification) and times
blocks of steps with the paths switched in turn, repeats interleaved, so every arm sees the same
model, the same load swings and the same warm caches. The paired ratio (each repeat's block
against the ``torch`` block next to it) is steadier than a comparison of two runs on a shared
machine. The arms' numerics differ only by float rounding (tests/core/methods/test_gpdfn.py).

    .venv/bin/python benchmarks/gpdfn_cpu_paths.py SCENE --gaussians 100000 --width 480 --threads 2 \\
        --steps 10 --repeats 6 --json benchmarks/results/gpdfn_cpu_paths.json

Speed is measured here, never asserted in tests.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

sys.path.insert(0, str(Path(__file__).resolve().parent))

import profile_step  # noqa: E402  (the arms and the Gaussians of the step profile)


def _switches() -> dict[str, Callable[[], None]]:
    """Arm name -> a function that sets GPDFN's CPU paths for that arm."""
    from esgs.core.methods.esgs import gpdfn

    sampling, fusion = gpdfn._sampling_kernels_apply, gpdfn._fusion_kernels_apply

    def use(sampling_kernels: bool, fusion_kernels: bool) -> Callable[[], None]:
        def apply() -> None:
            gpdfn._sampling_kernels_apply = sampling if sampling_kernels else (lambda tensor, table: False)
            gpdfn._fusion_kernels_apply = fusion if fusion_kernels else (lambda tensor: False)
        return apply

    return {"torch": use(False, False), "fusion kernels": use(False, True), "all kernels": use(True, True)}


def arm_order(names: list[str], repeat: int) -> list[str]:
    """The arms' order in block ``repeat``: each block starts with the next arm (no arm always runs
    first), and every other cycle through the arms runs backwards (no arm always runs after the
    same one, whose caches and clock state it would inherit)."""
    base = names if (repeat // len(names)) % 2 == 0 else names[::-1]
    shift = repeat % len(names)
    return base[shift:] + base[:shift]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("--gaussians", type=int, default=100_000)
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=10, help="steps per timed block")
    parser.add_argument("--repeats", type=int, default=6)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--priors", default="gt")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)

    from esgs.core.config import config_from_dict
    from esgs.core.methods import get_method
    from esgs.core.train.config import TrainConfig
    from esgs.core.train.trainer import Trainer

    switches = _switches()
    load_start = os.getloadavg()
    times: dict[str, list[float]] = {name: [] for name in switches}
    with tempfile.TemporaryDirectory() as out:
        config = config_from_dict(TrainConfig, {
            "scene": str(args.scene), "out": out, "iterations": 30_000, "width": args.width,
            "threads": args.threads, "seed": 0, "checkpoint_every": 0, "backend": "cpu",
            **profile_step.arms(args.priors)["full esgs"]})
        trainer = Trainer(config, method=get_method(config.method))
        trainer._initial_gaussians = lambda: profile_step._gaussians(trainer, args.gaussians, 0)
        trainer.setup()
        step = profile_step.FIRST_STEP
        for name in switches:  # every path compiled and warm before timing
            switches[name]()
            for _ in range(args.warmup):
                trainer.train_step(step)
                step += 1
        names = list(switches)
        for repeat in range(args.repeats):
            for name in arm_order(names, repeat):
                switches[name]()
                start = time.perf_counter()
                for _ in range(args.steps):
                    trainer.train_step(step)
                    step += 1
                times[name].append((time.perf_counter() - start) / args.steps * 1e3)
                print(f"[{repeat + 1}/{args.repeats}] {name:<16} {times[name][-1]:7.1f} ms/step", flush=True)
        switches["all kernels"]()
    summary: dict[str, Any] = {}
    for name, values in times.items():
        ratios = [value / base for value, base in zip(values, times["torch"])]
        summary[name] = {"ms_per_step": statistics.mean(values), "repeats_ms": values,
                         "paired_ratio_to_torch": statistics.mean(ratios),
                         "paired_ratio_spread": [min(ratios), max(ratios)]}
    print(f"\nmean of {args.repeats} blocks x {args.steps} full-ESGS steps, {args.gaussians:,} Gaussians, "
          f"width {args.width}, {args.threads} threads:")
    for name, row in summary.items():
        print(f"  {name:<16} {row['ms_per_step']:7.1f} ms/step  x{row['paired_ratio_to_torch']:.3f} the torch "
              f"paths (paired, {row['paired_ratio_spread'][0]:.3f}-{row['paired_ratio_spread'][1]:.3f})")
    if args.json:
        record = {"what": "full-ESGS step time with GPDFN's CPU paths switched in turn, one process",
                  "command": "python benchmarks/gpdfn_cpu_paths.py " + " ".join(argv if argv is not None else sys.argv[1:]),
                  "gaussians": args.gaussians, "width": args.width, "threads": args.threads, "steps": args.steps,
                  "repeats": args.repeats, "load_average_start": load_start, "load_average_end": os.getloadavg(),
                  "arms": summary}
        from esgs.core.io_utils import atomic_write_json

        args.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(args.json, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
