"""``esgs priors``: write a scene's prior maps in the standard format (priors/<method>/)."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "compute depth/normal prior maps for a scene (priors/<method>/)"

METHODS = ("sfm", "ndn")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", type=Path, help="scene folder (images/ + sparse/0)")
    parser.add_argument("--method", choices=METHODS, default="sfm",
                        help="sfm: sparse depth from the COLMAP points each view observes; "
                             "ndn: dense relative depth and normals from the NDN diffusion network")
    parser.add_argument("--max-error-px", type=float, default=2.0, help="drop points with a larger reprojection error")
    parser.add_argument("--min-track-length", type=int, default=2, help="drop points seen in fewer views")
    parser.add_argument("--weights", type=Path, default=None,
                        help="ndn: weights file or model folder (default: $ESGS_NDN_WEIGHTS, else the weights "
                             "shipped with the package)")
    parser.add_argument("--steps", type=int, default=None, help="ndn: DDIM steps (default: the model's)")
    parser.add_argument("--seed", type=int, default=0, help="ndn: seed of the starting noise")


def run(args: argparse.Namespace) -> int:
    if args.method == "ndn":
        return _run_ndn(args)
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


def _run_ndn(args: argparse.Namespace) -> int:
    from ..ndn.infer import write_ndn_priors
    from ..ndn.shipped import resolve_default_weights
    from ..progress import ConsoleProgress

    weights = resolve_default_weights(args.weights)
    bar = ConsoleProgress()
    count = write_ndn_priors(args.scene, weights, steps=args.steps, seed=args.seed, progress=bar)
    bar.close()
    print(f"wrote ndn priors for {count} views to {args.scene / 'priors' / 'ndn'} (weights: {weights})")
    return 0
