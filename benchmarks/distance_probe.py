"""Where the opaque Gaussians of finished runs lie off the true mesh: distance percentiles,
and how the distance splits by the number of training views whose frustum holds a centre.

    .venv/bin/python benchmarks/distance_probe.py SCENE RUN [RUN ...]

SCENE: the scene folder the runs trained on (``mesh/ground_truth.ply`` and ``sparse/0``);
RUN: a run folder with ``point_cloud.ply``. Centres with opacity >= 0.5, as the acceptance
study measures them; every 8th image is the held-out view, as in the study's split.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from esgs.core.colmap.io import read_model
from esgs.core.metrics.geometry import point_to_mesh_distances
from esgs.core.labels.mesh_io import load_mesh
from esgs.core.formats.ply import read_gaussians_ply
from esgs.core.formats.scene_dir import SceneDir
from esgs.core.formats.run_dir import RunDir

GROUPS = ((0, 0), (1, 1), (2, 3), (4, 10**6))


def views_seeing(points: np.ndarray, scene: Path, test_every: int = 8) -> np.ndarray:
    """[N] number of training views (all but every ``test_every``-th) whose frustum holds each point."""
    model = read_model(scene)
    count = np.zeros(len(points), np.int64)
    for index, image in enumerate(model.sorted_images()):
        if test_every and index % test_every == 0:
            continue
        camera = model.cameras[image.camera_id]
        world_to_camera = image.world_to_camera()
        local = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        z = local[:, 2]
        pixels = local @ camera.K().T
        u, v = pixels[:, 0] / np.maximum(z, 1e-9), pixels[:, 1] / np.maximum(z, 1e-9)
        count += (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    return count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("runs", type=Path, nargs="+")
    args = parser.parse_args()
    vertices, triangles = load_mesh(SceneDir(args.scene).ground_truth_mesh)
    for run in args.runs:
        gaussians = read_gaussians_ply(RunDir(run).point_cloud)
        opaque = 1.0 / (1.0 + np.exp(-gaussians.opacity_logit.reshape(-1))) >= 0.5
        points = gaussians.means[opaque].astype(np.float64)
        distance = point_to_mesh_distances(points, vertices, triangles)
        seen = views_seeing(points, args.scene)
        print(f"{run}: {len(points)} opaque centres, distance mean {distance.mean():.3f}, median "
              f"{np.median(distance):.3f}, p90 {np.percentile(distance, 90):.3f}, p99 {np.percentile(distance, 99):.3f}")
        for low, high in GROUPS:
            group = (seen >= low) & (seen <= high)
            label = f"{low}" if low == high else (f"{low}+" if high >= 10**6 else f"{low}-{high}")
            share = distance[group].sum() / max(distance.sum(), 1e-12)
            mean = distance[group].mean() if group.any() else float("nan")
            print(f"  seen by {label:>3} training views: {group.mean():5.1%} of the centres, mean {mean:.3f}, "
                  f"{share:5.1%} of the summed distance")


if __name__ == "__main__":
    main()
