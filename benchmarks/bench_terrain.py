"""Time terrain generation and camera rigs for every preset (prints figures, asserts nothing).

    .venv/bin/python benchmarks/bench_terrain.py [--repeat 3] [preset ...]
"""
from __future__ import annotations

import argparse
import time

from esgs.core.terrain import generate_terrain, list_presets, load_preset, make_camera_rig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("presets", nargs="*", help="presets to time (default: all)")
    parser.add_argument("--repeat", type=int, default=3, help="runs per preset; the best is reported")
    args = parser.parse_args()
    print(f"{'preset':22s} {'grid':>9s} {'craters':>7s} {'rocks':>6s} {'terrain_s':>9s} {'rig_s':>7s}")
    for name in args.presets or list_presets():
        config = load_preset(name)
        best_terrain = best_rig = float("inf")
        for _ in range(args.repeat):
            start = time.perf_counter()
            terrain = generate_terrain(config.terrain, seed=config.seed)
            middle = time.perf_counter()
            make_camera_rig(config.rig, config.render, terrain, seed=config.seed)
            end = time.perf_counter()
            best_terrain, best_rig = min(best_terrain, middle - start), min(best_rig, end - middle)
        grid = f"{terrain.resolution}^2"
        print(f"{name:22s} {grid:>9s} {len(terrain.craters):7d} {len(terrain.rocks):6d} {best_terrain:9.3f} {best_rig:7.3f}")


if __name__ == "__main__":
    main()
