"""Time the Gaussian centres -> mesh comparison (core/metrics/geometry.py) on a terrain-like case.

    .venv/bin/python benchmarks/bench_compare.py [--points 1000000] [--grid 512]

A height-field mesh of grid x grid cells (2 grid^2 triangles, 100 m across) and points
scattered around its surface (1% floaters up to 5 m above it). Prints the time of the
exact point -> mesh distances and of the full comparison (plus surface sampling, nearest
neighbours and statistics). The first call includes numba's compilation (cached on disk).
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def heightfield(grid: int, extent_m: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    coords = np.linspace(-extent_m / 2, extent_m / 2, grid + 1)
    xx, yy = np.meshgrid(coords, coords, indexing="ij")
    zz = 2.0 * np.sin(xx / 7.0) * np.cos(yy / 11.0)
    vertices = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()])
    index = np.arange(xx.size).reshape(grid + 1, grid + 1)
    a, b = index[:-1, :-1].ravel(), index[1:, :-1].ravel()
    c, d = index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    return vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--grid", type=int, default=512)
    args = parser.parse_args()

    from esgs.core.metrics.geometry import compare_points_to_mesh, point_to_mesh_distances

    vertices, faces = heightfield(args.grid)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-49.0, 49.0, (args.points, 2))
    z = 2.0 * np.sin(xy[:, 0] / 7.0) * np.cos(xy[:, 1] / 11.0) + rng.normal(0.0, 0.05, args.points)
    floaters = rng.random(args.points) < 0.01
    z[floaters] += rng.uniform(0.5, 5.0, floaters.sum())
    points = np.column_stack([xy, z])
    point_to_mesh_distances(points[:1000], vertices, faces)  # compile the kernel
    start = time.perf_counter()
    distances = point_to_mesh_distances(points, vertices, faces)
    elapsed = time.perf_counter() - start
    print(f"{args.points:,} points -> {len(faces):,} triangles: {elapsed:.2f} s "
          f"({args.points / elapsed / 1e3:.0f}k points/s), mean distance {distances.mean():.4f} m")
    start = time.perf_counter()
    result = compare_points_to_mesh(points, vertices, faces, opacities=rng.random(args.points))
    print(f"full comparison (100k surface samples): {time.perf_counter() - start:.2f} s, "
          f"F-score {result.summary['fscore']:.3f}")


if __name__ == "__main__":
    main()
