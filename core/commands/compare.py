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
    parser.add_argument("--threshold", type=float, default=None,
                        help="distance in scene units under which a point counts as matched (default: 0.05; with "
                             "--scene, 1 %% of the median camera-to-surface distance)")
    parser.add_argument("--scene", type=Path, default=None,
                        help="the scene folder the run trained on: recall then counts only the part of the mesh "
                             "its training cameras saw (docs/metrics.md)")
    parser.add_argument("--test-every", type=int, default=8,
                        help="with --scene: the run's held-out split (every Nth image; default 8, 0 = none)")
    parser.add_argument("--samples", type=int, default=100_000, help="points sampled on the mesh (default: 100000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the surface sampling (default: 0)")
    parser.add_argument("--out", type=Path, help="write the report as JSON here (atomically)")


def run(args: argparse.Namespace) -> int:
    import json

    from ..metrics.geometry import compare_ply_to_mesh
    from ..io_utils import atomic_write_json

    cameras, threshold = None, 0.05 if args.threshold is None else args.threshold
    if args.scene is not None:
        from ..colmap.io import read_model
        from ..metrics.visibility import cameras_from_colmap, training_image_names

        model = read_model(args.scene)
        names = training_image_names([image.name for image in model.images.values()], args.test_every)
        cameras = cameras_from_colmap(model, names)
        threshold = args.threshold  # None: scaled to the scene
    result = compare_ply_to_mesh(args.gaussians, args.mesh, opacity_min=args.opacity_min, threshold_m=threshold,
                                 n_surface_samples=args.samples, seed=args.seed, cameras=cameras)
    summary = dict(result.summary, gaussians_file=str(args.gaussians), mesh_file=str(args.mesh))
    if args.scene is not None:
        summary["scene"] = str(args.scene)
    if args.out:
        atomic_write_json(args.out, summary)
    print(json.dumps(summary, indent=2))
    return 0
