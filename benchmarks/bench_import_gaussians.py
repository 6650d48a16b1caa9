"""Time importing a 3DGS PLY of N Gaussians into Blender (bpy module).

    .venv/bin/python benchmarks/bench_import_gaussians.py [--count 1000000] [--sh-degree 3]

Prints the PLY write time (not part of the import), the import time (read + attributes +
point cloud + geometry-node modifier) and the first evaluation of the display modifier.
Target: 1M Gaussians import in <= 5 s.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=1_000_000)
    parser.add_argument("--sh-degree", type=int, default=3)
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()

    import bpy

    import esgs
    from esgs.core.formats.ply import GaussianPly, write_gaussians_ply
    from esgs.esgs_addon.gaussians_import import import_gaussians, remove_object

    bpy.ops.wm.read_factory_settings(use_empty=True)
    esgs.register()
    rng = np.random.default_rng(0)
    n, rest = args.count, (args.sh_degree + 1) ** 2 - 1
    gaussians = GaussianPly(
        means=rng.normal(size=(n, 3)), normals=np.zeros((n, 3)), sh_dc=rng.normal(size=(n, 3)),
        sh_rest=rng.normal(scale=0.1, size=(n, rest, 3)), opacity_logit=rng.normal(size=n),
        log_scales=rng.normal(-4, 0.5, size=(n, 3)), quats_wxyz=rng.normal(size=(n, 4)))
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "point_cloud.ply"
        start = time.perf_counter()
        write_gaussians_ply(path, gaussians)
        print(f"write PLY ({n:,} Gaussians, SH degree {args.sh_degree}, "
              f"{path.stat().st_size / 1e6:.0f} MB): {time.perf_counter() - start:.2f} s")
        for attempt in range(args.repeat):
            start = time.perf_counter()
            obj = import_gaussians(path, max_display=200_000)
            imported = time.perf_counter() - start
            start = time.perf_counter()
            depsgraph = bpy.context.evaluated_depsgraph_get()
            depsgraph.update()
            shown = len(obj.evaluated_get(depsgraph).data.points)
            evaluated = time.perf_counter() - start
            print(f"run {attempt + 1}: import {imported:.2f} s (target <= 5 s), "
                  f"first display evaluation {evaluated:.2f} s ({shown:,} shown)")
            remove_object(obj)


if __name__ == "__main__":
    main()
