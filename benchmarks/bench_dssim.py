"""The training loss's D-SSIM: the Numba kernels (``core/train/fused_ssim.py``) against the torch statement.

Forward and backward of ``1 - mean(SSIM)`` of a rendered ``[H, W, 3]`` float32 image against its
target, at each size, the two paths taking turns over the repeats (so a change of the machine's
load touches both alike); the minimum and median of each path's times are reported. Also checks
that both give the same loss (to float32 rounding) before timing.

    python benchmarks/bench_dssim.py --sizes 480x270 960x540 1920x1080 --threads 2 --repeats 15 \\
        --json benchmarks/results/dssim_kernels.json

``--train-scene SCENE --out DIR`` then also trains ``esgs train SCENE`` (the defaults, ``--train-args``
added) twice, once with each path, and reports both runs' held-out PSNR / SSIM / LPIPS, Gaussian
count and training seconds: the kernels round differently from torch's convolutions, and
densification turns a rounding difference into a different run.

Speed is measured here, never asserted in tests. Run it on an otherwise idle machine.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["480x270", "1920x1080"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--train-scene", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=None, help="run folders of --train-scene")
    parser.add_argument("--train-args", default="--iterations 300 --width 240 --threads 2 --seed 0",
                        help="esgs train options of both runs")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.train_scene is not None and args.out is None:
        parser.error("--train-scene needs --out")

    import numba
    import torch

    from esgs.core.metrics.image import ssim_map
    from esgs.core.train.fused_ssim import dssim

    torch.set_num_threads(args.threads)
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))

    def torch_statement(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return 1.0 - ssim_map(image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]).mean()

    paths = {"torch statement": torch_statement, "numba kernels": dssim}
    rows = {}
    load_start = os.getloadavg()
    for size in args.sizes:
        width, height = (int(v) for v in size.split("x"))
        generator = torch.Generator().manual_seed(0)
        target = torch.rand(height, width, 3, generator=generator)
        image = (target + 0.05 * torch.randn(height, width, 3, generator=generator)).clamp(0, 1)
        losses = {name: float(path(image, target)) for name, path in paths.items()}
        times: dict[str, dict[str, list[float]]] = {name: {"forward": [], "backward": []} for name in paths}
        for repeat in range(args.repeats + 1):  # the first round compiles and warms up
            for name, path in paths.items():
                rendered = image.clone().requires_grad_()
                started = time.perf_counter()
                loss = path(rendered, target)
                middle = time.perf_counter()
                loss.backward()
                ended = time.perf_counter()
                if repeat:
                    times[name]["forward"].append(middle - started)
                    times[name]["backward"].append(ended - middle)
        row = {"loss": losses}
        for name, parts in times.items():
            total = [f + b for f, b in zip(parts["forward"], parts["backward"])]
            row[name] = {"forward_ms_median": 1e3 * statistics.median(parts["forward"]),
                         "backward_ms_median": 1e3 * statistics.median(parts["backward"]),
                         "total_ms_median": 1e3 * statistics.median(total), "total_ms_min": 1e3 * min(total)}
        row["speed_up_median"] = row["torch statement"]["total_ms_median"] / row["numba kernels"]["total_ms_median"]
        rows[size] = row
        print(f"{size}: torch {row['torch statement']['forward_ms_median']:.1f} + "
              f"{row['torch statement']['backward_ms_median']:.1f} ms, kernels "
              f"{row['numba kernels']['forward_ms_median']:.1f} + {row['numba kernels']['backward_ms_median']:.1f} ms "
              f"(forward + backward, medians): {row['speed_up_median']:.1f}x; losses {losses}", flush=True)
    trained = _train_both(args, torch_statement) if args.train_scene is not None else None
    result = {"command": "python " + " ".join([sys.argv[0], *(argv if argv is not None else sys.argv[1:])]),
              "threads": args.threads, "repeats": args.repeats, "load_average_start": load_start,
              "load_average_end": os.getloadavg(), "sizes": rows,
              "training": trained}
    if args.json:
        from esgs.core.io_utils import atomic_write_json

        atomic_write_json(args.json, result)
    return 0


def _train_both(args: argparse.Namespace, torch_statement) -> dict:
    """Train the scene with each D-SSIM path (the loss term's function swapped in this process)."""
    import json
    import shlex

    from esgs.core.cli import main as esgs_main
    from esgs.core.formats.run_dir import RunDir
    from esgs.core.train import losses

    kernels = losses.dssim
    runs = {}
    for name, path in (("numba kernels", kernels), ("torch statement", torch_statement)):
        out = args.out / name.replace(" ", "_")
        losses.dssim = path
        try:
            code = esgs_main(["train", str(args.train_scene), "--out", str(out), "--quiet",
                              *shlex.split(args.train_args)])
        finally:
            losses.dssim = kernels
        if code:
            raise SystemExit(f"esgs train failed ({code}) for the {name} run; see {out}")
        metrics = json.loads(RunDir(out).metrics.read_text())
        result = json.loads(RunDir(out).result.read_text())
        runs[name] = {"psnr": metrics["psnr"], "ssim": metrics["ssim"], "lpips": metrics.get("lpips"),
                      "n_gaussians": result["n_gaussians"], "train_s": result["train_s"]}
        print(f"{name}: {runs[name]}", flush=True)
    return {"scene": str(args.train_scene), "args": args.train_args, "runs": runs}


if __name__ == "__main__":
    raise SystemExit(main())
