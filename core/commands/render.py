"""``esgs render RUN_DIR --camera NAME | --all``: render a trained run from its scene's cameras."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "render a trained run from one or all of its scene's cameras (PNG, optional depth EXR)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", type=Path, help="run folder written by esgs train")
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--camera", action="append", metavar="NAME",
                       help="image name (or stem) of a camera to render; repeat for several")
    which.add_argument("--all", action="store_true", help="render every camera (train and test)")
    parser.add_argument("--output", type=Path, default=None, help="folder for the images (default RUN/renders/cameras)")
    parser.add_argument("--depth", action="store_true", help="also write expected depth as <stem>_depth.exr")
    parser.add_argument("--backend", choices=("auto", "cpu", "reference", "cuda"), default=None,
                        help="rasterizer backend (default: the run's)")


def run(args: argparse.Namespace) -> int:
    from ..methods import render_run

    written = render_run(args.run_dir, cameras=None if args.all else args.camera, output=args.output,
                         depth=args.depth, backend=args.backend)
    for path in written:
        print(path)
    return 0
