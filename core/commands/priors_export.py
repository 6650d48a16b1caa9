"""``esgs priors-export``: a scene's depth priors in another tool's layout (the 3DGS reference code's)."""
from __future__ import annotations

import argparse
from pathlib import Path

NAME = "priors-export"
HELP = ("export depth priors for other trainers: --format 3dgs writes depths/<stem>.png and "
        "sparse/0/depth_params.json (the 3DGS reference code's depth regularisation)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..priors.export import FORMATS

    parser.add_argument("scene", type=Path, help="scene folder (sparse/0 + priors/<source>/)")
    parser.add_argument("--source", required=True,
                        help="prior source to export (priors/<source>/: auto, ndn, labels, sfm, gt...)")
    parser.add_argument("--format", choices=FORMATS, default="3dgs", help="layout to write (default: 3dgs)")
    parser.add_argument("--out", type=Path, default=None,
                        help="folder that gets depths/ and sparse/0/depth_params.json (default: the scene; "
                             "point the reference code's -s at a folder holding both the COLMAP model and these)")


def run(args: argparse.Namespace) -> int:
    from ..priors.export import export_3dgs_depths

    result = export_3dgs_depths(args.scene, args.source, args.out)
    print(f"wrote {result.views} inverse-depth PNGs to {result.depths} and {result.depth_params} "
          f"(scale {result.scale:.6g}, offset 0; {100 * result.coverage:.0f}% of pixels have a value)")
    if result.coverage < 0.5:
        print("note: the 3DGS reference code has no depth mask; pixels without a prior read as infinitely far")
    return 0
