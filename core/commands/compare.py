"""``esgs compare``: distances of trained Gaussian centres to a ground-truth mesh."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "compare a trained point_cloud.ply with a ground-truth mesh (distances, precision/recall/F-score)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("gaussians", type=Path, help="3DGS PLY of the trained Gaussians (RUN/point_cloud.ply)")
    parser.add_argument("mesh", type=Path, help="ground-truth mesh (SCENE/mesh/ground_truth.ply, OBJ, GLB...)")
    parser.add_argument("--opacity-min", type=float, default=0.5,
                        help="Gaussians below this activated opacity are left out of the filtered figures (default: 0.5)")
    parser.add_argument("--threshold", type=float, default=0.05,
                        help="distance in scene units under which a point counts as matched (default: 0.05)")
    parser.add_argument("--samples", type=int, default=100_000, help="points sampled on the mesh (default: 100000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the surface sampling (default: 0)")
    parser.add_argument("--out", type=Path, help="write the report as JSON here (atomically)")


def run(args: argparse.Namespace) -> int:
    import json

    from ..metrics.geometry import compare_ply_to_mesh
    from ..io_utils import atomic_write_json

    result = compare_ply_to_mesh(args.gaussians, args.mesh, opacity_min=args.opacity_min,
                                 threshold_m=args.threshold, n_surface_samples=args.samples, seed=args.seed)
    summary = dict(result.summary, gaussians_file=str(args.gaussians), mesh_file=str(args.mesh))
    if args.out:
        atomic_write_json(args.out, summary)
    print(json.dumps(summary, indent=2))
    return 0
