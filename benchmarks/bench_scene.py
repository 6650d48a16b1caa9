"""Benchmark: generate, render and export a 30-view 480x270 synthetic Mars scene.

Target: <= 3 minutes for the whole job (terrain + Blender scene + Cycles CPU renders +
priors + mesh + COLMAP model) on the 2-core development machine. Prints the time of each
stage, seconds per view and the machine's load average (the machine is shared: the load
says how much of it the benchmark had).

    .venv/bin/python benchmarks/bench_scene.py [--preset cratered_plain] [--views 30]
        [--resolution 480x270] [--samples 0 (= the preset's)] [--sfm]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path


def main() -> None:
    from esgs.core.commands.scene import parse_resolution
    from esgs.core.formats.scene_dir import SceneDir

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cratered_plain")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--views", type=int, default=30)
    parser.add_argument("--resolution", type=parse_resolution, default=(480, 270))
    parser.add_argument("--samples", type=int, default=0, help="Cycles samples (0 = the preset's)")
    parser.add_argument("--sfm", action="store_true", help="also time pycolmap SfM on the renders")
    parser.add_argument("--keep", type=Path, default=None, help="keep the scene folder here")
    args = parser.parse_args()

    import bpy

    from esgs.core.terrain import load_preset
    from esgs.esgs_addon.render_dataset import render_dataset
    from esgs.esgs_addon.terrain_scene import build_terrain_scene

    load_before = os.getloadavg()
    wall_start, cpu_start = time.perf_counter(), time.process_time()
    config = load_preset(args.preset, seed=args.seed, views=args.views, resolution=args.resolution,
                         samples=args.samples or None)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    objects = build_terrain_scene(config)
    built = time.perf_counter()
    render_times = []

    def progress(event):
        if event.stage == "render" and "view_s" in event.metrics:
            render_times.append(event.metrics["view_s"])

    workdir = Path(tempfile.mkdtemp(prefix="esgs_bench_scene_"))
    try:
        out = render_dataset(objects, workdir / "scene", progress=progress, sfm=args.sfm)
        done = time.perf_counter()
        info = json.loads(SceneDir(out).provenance.read_text())
        if args.keep:
            shutil.copytree(out, args.keep, dirs_exist_ok=False)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    total = done - wall_start
    print(f"scene {args.preset} seed {args.seed}: {args.views} views at {args.resolution[0]}x{args.resolution[1]}, "
          f"{config.render.samples} samples, {len(objects['rocks'])} rocks, "
          f"{config.terrain.resolution}^2 heightfield")
    print(f"generate + build scene : {built - wall_start:7.1f} s")
    print(f"render + export        : {done - built:7.1f} s  ({sum(render_times) / max(len(render_times), 1):.2f} s per view rendered)")
    if info.get("sfm"):
        print(f"SfM registered         : {info['sfm']['registered']}/{info['sfm']['total']}")
    print(f"total                  : {total:7.1f} s  (target <= 180 s: {'met' if total <= 180 else 'NOT met'})")
    print(f"process CPU time       : {time.process_time() - cpu_start:7.1f} s on {os.cpu_count()} cores")
    print(f"load average before/after: {load_before[0]:.1f} / {os.getloadavg()[0]:.1f}")
    print(f"points3D: {info['points3d']}")


if __name__ == "__main__":
    main()
