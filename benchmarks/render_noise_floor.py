"""How close two Cycles renders of the same synthetic scene are: the noise floor of held-out PSNR.

A scene from ``esgs scene`` is rendered with 16 samples and denoised; its images carry the
render's noise, which no reconstruction can predict for a view it did not train on. This
renders the scene again with the same settings and another Cycles noise seed (``--noise-seed``;
everything else, cameras included, is the scene's own) and reports, per view, the PSNR of one
render against the other. With independent noise of equal power, a prediction free of noise
would score about 3 dB above that figure against either render: the ceiling of a held-out
view's PSNR. Views are grouped into those whose ground-truth mask marks sky and those without.

    .venv/bin/python benchmarks/render_noise_floor.py --mesh ../shared/data/mars_landform/terrain.glb \\
        --rig mixed --views 36 --seed 4 --resolution 480x270 --samples 16 --points-per-view 3000 \\
        --scene /work/runs/mixed_s4_480 --noise-seed 7 --out /work/runs/noise/mixed_s4_480_seed7 \\
        --json benchmarks/results/render_noise_floor_mixed_s4_480.json

``--scene`` is the existing render (made with the same ``esgs scene`` arguments, Cycles' default
seed 0); the arguments before it are passed to the scene generator unchanged. Runs Blender
(bpy) in this process.
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np


def render_with_noise_seed(scene_arguments: list[str], out: Path, noise_seed: int) -> None:
    """Run the scene generator in-process with Cycles' noise seed set to ``noise_seed``."""
    from esgs.esgs_addon import make_scene, terrain_scene

    apply = terrain_scene.apply_render_settings

    def seeded(scene, render_config) -> None:  # the generator's settings, then another noise pattern
        apply(scene, render_config)
        scene.cycles.seed = noise_seed

    terrain_scene.apply_render_settings = seeded
    try:
        code = make_scene.main([*scene_arguments, "--out", str(out)])
    finally:
        terrain_scene.apply_render_settings = apply
    if code != 0:
        raise SystemExit(f"scene generator failed with exit code {code}")
    _record_noise_seed(out, noise_seed)


def _record_noise_seed(out: Path, noise_seed: int) -> None:
    """Add the Cycles noise seed to the render's provenance (``scene.json``), so a later run that
    reuses the folder can tell whether it holds the seed it asks for."""
    import json

    from esgs.core.formats.scene_dir import SceneDir
    from esgs.core.io_utils import atomic_write_json

    path = SceneDir(out).provenance
    record = json.loads(path.read_text()) if path.is_file() else {}
    record["cycles_noise_seed"] = noise_seed
    atomic_write_json(path, record)


def check_reused_render(out: Path, noise_seed: int) -> None:
    """Refuse to reuse ``out`` unless its provenance records ``noise_seed``."""
    import json

    from esgs.core.formats.scene_dir import SceneDir

    path = SceneDir(out).provenance
    recorded = json.loads(path.read_text()).get("cycles_noise_seed") if path.is_file() else None
    if recorded is None:
        # a render from before the seed was recorded (or not this script's): its seed is unknown
        raise SystemExit(f"{out} holds a render whose Cycles noise seed is not recorded ({path} has no "
                         "cycles_noise_seed): pass another --out to render afresh")
    if recorded != noise_seed:
        raise SystemExit(f"{out} holds a render with Cycles noise seed {recorded} (from {path}), not "
                         f"{noise_seed}: pass another --out to render afresh, or --noise-seed {recorded} to reuse it")


def compare(first: Path, second: Path) -> list[dict]:
    """Per view: PSNR of ``first``'s image against ``second``'s and whether its mask marks sky."""
    import cv2

    from esgs.core.formats.scene_dir import SceneDir

    first_dir, second_dir = SceneDir(first), SceneDir(second)
    rows = []
    for image in sorted(first_dir.images.glob("*.png")):
        other = second_dir.image(image.name)
        if not other.exists():
            raise SystemExit(f"{other} is missing: render both scenes with the same arguments")
        a = cv2.imread(str(image)).astype(np.float64) / 255.0
        b = cv2.imread(str(other)).astype(np.float64) / 255.0
        mse = float(((a - b) ** 2).mean())
        mask_path = first_dir.mask_map("gt", image.name)
        sky = False
        if mask_path.exists():  # 0 = sky / no surface in the ground-truth masks
            sky = bool((cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE) == 0).any())
        rows.append({"view": image.stem, "psnr_db": 10 * np.log10(1.0 / mse) if mse > 0 else None, "sky": sky})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, required=True, help="the existing render (Cycles seed 0)")
    parser.add_argument("--noise-seed", type=int, default=7)
    parser.add_argument("--out", type=Path, required=True, help="folder of the second render")
    parser.add_argument("--json", type=Path, default=None)
    args, scene_arguments = parser.parse_known_args(argv)
    from esgs.core.formats.scene_dir import SceneDir

    if not SceneDir(args.out).images.exists():
        render_with_noise_seed(scene_arguments, args.out, args.noise_seed)
    else:
        check_reused_render(args.out, args.noise_seed)
    rows = compare(args.scene, args.out)
    if any(row["psnr_db"] is None for row in rows):
        raise SystemExit("identical images: the noise seed did not reach the renderer")
    groups = {}
    for label, keep in (("views with sky", True), ("views without sky", False)):
        values = [row["psnr_db"] for row in rows if row["sky"] == keep]
        if values:
            groups[label] = {"views": len(values), "mean_psnr_db": statistics.mean(values),
                             "min_psnr_db": min(values), "max_psnr_db": max(values),
                             "noise_free_ceiling_db": statistics.mean(values) + 10 * np.log10(2.0)}
    for label, group in groups.items():
        print(f"{label}: {group['views']} views, render against render {group['mean_psnr_db']:.2f} dB "
              f"({group['min_psnr_db']:.2f}-{group['max_psnr_db']:.2f}); a noise-free prediction ~"
              f"{group['noise_free_ceiling_db']:.2f} dB")
    if args.json:
        record = {"what": "PSNR between two Cycles renders of one scene with different noise seeds",
                  "command": "python benchmarks/render_noise_floor.py " + " ".join(argv if argv is not None else sys.argv[1:]),
                  "scene": str(args.scene), "second_render": str(args.out), "noise_seed": args.noise_seed,
                  "groups": groups, "views": rows}
        from esgs.core.io_utils import atomic_write_json

        args.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(args.json, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
