"""``esgs eval RUN_DIR``: measure a trained run on its held-out views (writes metrics.json)."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "evaluate a training run on its held-out views: PSNR, SSIM, LPIPS (writes RUN/metrics.json)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", type=Path, help="run folder written by esgs train")
    parser.add_argument("--backend", choices=("auto", "cpu", "reference", "cuda"), default=None,
                        help="rasterizer backend (default: the run's)")
    parser.add_argument("--no-renders", action="store_true", help="do not write renders/test/*.png")
    parser.add_argument("--no-lpips", action="store_true", help="skip LPIPS")
    parser.add_argument("--json", action="store_true", help="print the metrics as JSON")


def run(args: argparse.Namespace) -> int:
    import json

    from ..methods import evaluate_run

    metrics = evaluate_run(args.run_dir, backend=args.backend, save_renders=not args.no_renders,
                           use_lpips=not args.no_lpips)
    if args.json:
        print(json.dumps(metrics, indent=2))
        return 0
    for row in metrics["views"]:
        lpips = "n/a" if row["lpips"] is None else f"{row['lpips']:.4f}"
        print(f"{row['name']:<32} PSNR {row['psnr']:7.3f}  SSIM {row['ssim']:.4f}  LPIPS {lpips}")
    lpips = metrics["lpips"]
    lpips_text = f"{lpips:.4f}" if lpips is not None else f"n/a ({metrics['lpips_unavailable']})"
    print(f"mean over {metrics['views_count']} {metrics['split']} views: PSNR {metrics['psnr']:.3f} dB, "
          f"SSIM {metrics['ssim']:.4f}, LPIPS {lpips_text}")
    return 0
