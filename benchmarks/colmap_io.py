"""Time COLMAP model reading/writing on a synthetic model of realistic size.

    .venv/bin/python benchmarks/colmap_io.py [--images 100] [--keypoints 8000] [--points 100000]

Prints seconds for: the checked parse alone, read_model (parse + pycolmap + conversion)
and write_model, in binary and text form.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from esgs.core.colmap import Camera, ColmapModel, Image, Point3D, parse_model, read_model, write_model


def synthetic_model(num_images: int, num_keypoints: int, num_points: int, seed: int = 0) -> ColmapModel:
    """Random but consistent model: every point seen in 3 random images."""
    rng = np.random.default_rng(seed)
    camera = Camera(1, "OPENCV", 1920, 1080, np.array([1500.0, 1500.0, 960.0, 540.0, -0.1, 0.01, 0.0, 0.0]))
    point3d_ids = np.full((num_images, num_keypoints), -1, dtype=np.int64)
    tracks = []
    next_slot = np.zeros(num_images, dtype=np.int64)
    for point_id in range(1, num_points + 1):
        seen = rng.choice(num_images, 3, replace=False)
        if np.any(next_slot[seen] >= num_keypoints):
            break
        track = [(int(i) + 1, int(next_slot[i])) for i in seen]
        point3d_ids[seen, next_slot[seen]] = point_id
        next_slot[seen] += 1
        tracks.append(track)
    images = {}
    for index in range(num_images):
        quat = rng.normal(size=4)
        images[index + 1] = Image(
            index + 1, f"frame_{index:05d}.jpg", 1, quat / np.linalg.norm(quat), rng.normal(size=3),
            rng.uniform(0, 1000, (num_keypoints, 2)), point3d_ids[index],
        )
    points = {
        i + 1: Point3D(i + 1, rng.normal(size=3), rng.integers(0, 256, 3).astype(np.uint8), float(rng.uniform()),
                       np.array([t[0] for t in track]), np.array([t[1] for t in track]))
        for i, track in enumerate(tracks)
    }
    return ColmapModel({1: camera}, images, points)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=100)
    parser.add_argument("--keypoints", type=int, default=8000)
    parser.add_argument("--points", type=int, default=100_000)
    args = parser.parse_args()
    model = synthetic_model(args.images, args.keypoints, args.points)
    print(f"model: {len(model.images)} images x {args.keypoints} keypoints, {len(model.points)} points")
    with tempfile.TemporaryDirectory() as folder:
        for binary in (True, False):
            label = "bin" if binary else "txt"
            path = Path(folder) / label
            start = time.perf_counter()
            write_model(model, path, binary=binary)
            written = time.perf_counter()
            parse_model(path)
            parsed = time.perf_counter()
            read_model(path)
            done = time.perf_counter()
            print(f"{label}: write_model {written - start:.2f} s, parse only {parsed - written:.2f} s, "
                  f"read_model {done - parsed:.2f} s")


if __name__ == "__main__":
    main()
