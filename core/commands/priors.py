"""``esgs priors``: write a scene's prior maps in the standard format (priors/<method>/)."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "compute depth/normal prior maps for a scene (priors/<method>/)"

METHODS = ("sfm",)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", type=Path, help="scene folder (images/ + sparse/0)")
    parser.add_argument("--method", choices=METHODS, default="sfm",
                        help="sfm: sparse depth from the COLMAP points each view observes")
    parser.add_argument("--max-error-px", type=float, default=2.0, help="drop points with a larger reprojection error")
    parser.add_argument("--min-track-length", type=int, default=2, help="drop points seen in fewer views")


def run(args: argparse.Namespace) -> int:
    from ..colmap import read_model
    from ..priors.sfm import write_sfm_priors
    from ..progress import ConsoleProgress

    model = read_model(args.scene)
    bar = ConsoleProgress()
    count = write_sfm_priors(args.scene, model, progress=bar, max_error_px=args.max_error_px,
                             min_track_length=args.min_track_length)
    bar.close()
    print(f"wrote {args.method} priors for {count} views to {args.scene / 'priors' / args.method}")
    return 0
