"""Generate a synthetic Mars terrain and its cameras, and save a shaded overview map.

No Blender needed:

    .venv/bin/python examples/terrain_preview.py --preset dune_field --seed 3 --out dune_field.png

Prints the scene's size and timing; the PNG shows the relief lit by the scene's sun
(north up), sand tinted, rocks as dark dots, camera positions in red and where each
camera's central ray meets the ground in green.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parent))  # esgs_loader.py
from esgs_loader import esgs_module, load_esgs  # noqa: E402


def main() -> int:
    esgs = load_esgs()
    ESGSError = esgs_module(esgs, "core.errors").ESGSError  # noqa: N806 - a class
    terrain_module = esgs_module(esgs, "core.terrain")
    generate_terrain, list_presets = terrain_module.generate_terrain, terrain_module.list_presets
    load_preset, make_camera_rig = terrain_module.load_preset, terrain_module.make_camera_rig
    overview_image = esgs_module(esgs, "core.terrain.preview").overview_image
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cratered_plain", choices=list_presets())
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--views", type=int, default=None)
    parser.add_argument("--out", default="terrain_preview.png")
    args = parser.parse_args()
    try:
        config = load_preset(args.preset, seed=args.seed, views=args.views)
    except ESGSError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    start = time.perf_counter()
    terrain = generate_terrain(config.terrain, seed=config.seed)
    cameras = make_camera_rig(config.rig, config.render, terrain, seed=config.seed)
    elapsed = time.perf_counter() - start
    image = overview_image(terrain, config.sun_direction(), cameras)
    cv2.imwrite(args.out, image[..., ::-1])
    print(f"{config.name} seed {config.seed}: {terrain.resolution}^2 samples over {terrain.extent_m:g} m, "
          f"{len(terrain.craters)} craters, {len(terrain.rocks)} rocks, {len(cameras)} cameras "
          f"({config.rig.kind}) in {elapsed:.2f} s -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
