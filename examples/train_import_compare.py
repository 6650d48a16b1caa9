"""Train Gaussians headless, import them into Blender and measure them against the ground truth.

Run either way:

    blender -b --python examples/train_import_compare.py -- --out OUT [--scene SCENE] [--iterations 300]
    python examples/train_import_compare.py --out OUT [--scene SCENE]          (bpy module)

Without ``--scene`` a tiny synthetic Mars scene (preset ``cratered_plain``, 8 views of
160x90) is generated into OUT/scene first. Then:

1. the scene's cameras are imported (ESGS COLMAP import) for a point of view;
2. the trainer runs in a separate process (``esgs train``), blocking, with console progress;
3. RUN/point_cloud.ply is imported as Gaussians;
4. their centres are compared with SCENE/mesh/ground_truth.ply (distances, precision,
   recall, F-score), written to OUT/compare.json, and shown as a heat map;
5. OUT/result.blend is saved and OUT/heat_map.png rendered with Cycles on the CPU.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # esgs_loader.py, also under blender --python
from esgs_loader import esgs_module as module, load_esgs, script_arguments  # noqa: E402


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder (scene, run, report, .blend, picture)")
    parser.add_argument("--scene", type=Path, help="an existing scene folder with mesh/ground_truth.ply")
    parser.add_argument("--preset", default="cratered_plain", help="scene preset when generating (default: cratered_plain)")
    parser.add_argument("--views", type=int, default=8, help="views of the generated scene (default: 8)")
    parser.add_argument("--resolution", default="160x90", help="image size of the generated scene (default: 160x90)")
    parser.add_argument("--iterations", type=int, default=300, help="training steps (default: 300)")
    parser.add_argument("--max-gaussians", type=int, default=20_000,
                        help="cap on the number of Gaussians, keeps the CPU demo short (default: 20000)")
    parser.add_argument("--opacity-min", type=float, default=0.5, help="opacity filter of the statistics (default: 0.5)")
    parser.add_argument("--threshold", type=float, default=0.1, help="match distance in metres (default: 0.1)")
    parser.add_argument("--render-size", default="480x270", help="size of the heat-map picture (default: 480x270)")
    return parser.parse_args(argv)


def generate_scene(esgs, args: argparse.Namespace) -> Path:
    scene_command = module(esgs, "core.commands.scene")
    make_scene = module(esgs, "esgs_addon.make_scene")
    progress = module(esgs, "core.progress")
    width, height = scene_command.parse_resolution(args.resolution)
    job = scene_command.SceneJob(preset=args.preset, views=args.views, width=width, height=height, samples=8,
                                 points_per_view=500, overwrite=True)
    out = args.out / "scene"
    console = progress.ConsoleProgress()
    try:
        make_scene.make_scene(job, out, progress=console)
    finally:
        console.close()
    return out


def render_heat_map(bpy, camera, path: Path, size: str) -> None:
    scene = bpy.context.scene
    width, height = (int(v) for v in size.lower().split("x"))
    scene.camera = camera
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 16
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


def main(argv: list[str]) -> int:
    import bpy

    esgs = load_esgs()
    args = parse(argv)
    args.out = args.out.resolve()
    args.out.mkdir(parents=True, exist_ok=True)
    errors = module(esgs, "core.errors")
    started = time.perf_counter()
    try:
        scene_dir = args.scene.resolve() if args.scene else generate_scene(esgs, args)
        mesh_path = module(esgs, "core.scene_dir").SceneDir(scene_dir).ground_truth_mesh
        if not mesh_path.is_file():
            raise errors.DatasetError("the scene has no ground-truth mesh", path=mesh_path,
                                      hint="use a synthetic scene (esgs scene) or omit --scene")

        bpy.ops.wm.read_factory_settings(use_empty=True)
        esgs.register()
        colmap_scene = module(esgs, "esgs_addon.colmap_scene")
        training_job = module(esgs, "esgs_addon.training_job")
        compare_mesh = module(esgs, "esgs_addon.compare_mesh")
        gaussian_nodes = module(esgs, "esgs_addon.gaussian_nodes")

        imported = colmap_scene.import_colmap_scene(scene_dir, colmap_scene.ColmapImportOptions(import_points=False))
        train_config = module(esgs, "core.train.config").TrainConfig(max_gaussians=args.max_gaussians)
        result = training_job.train_scene(scene_dir, args.out / "run", args.iterations, config=train_config)
        state = result["state"]
        if result["object"] is None:
            print(f"training {state.status}: {state.error}", file=sys.stderr)
            return 1
        gaussians = result["object"]
        # the mesh file is in the scene's (COLMAP) frame, like the trained Gaussians
        summary = compare_mesh.compare_to_mesh(gaussians, mesh_path, opacity_min=args.opacity_min,
                                               threshold_m=args.threshold, out_json=args.out / "compare.json")
        # the picture shows every Gaussian (short runs reset opacities often, so most are
        # faint); the statistics above used the opacity filter
        gaussian_nodes.set_display_inputs(gaussians, opacity_min=0.0)
        bpy.ops.wm.save_as_mainfile(filepath=str(args.out / "result.blend"))
        render_heat_map(bpy, imported["cameras"][0], args.out / "heat_map.png", args.render_size)
    except errors.ESGSError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1

    filtered = summary["gaussians_to_mesh_filtered"]
    print(json.dumps({key: summary[key] for key in ("n_gaussians", "n_gaussians_filtered", "precision", "recall",
                                                     "fscore")}, indent=2))
    if filtered["mean"] is not None:
        print(f"Gaussian centres -> ground truth (opacity >= {args.opacity_min:g}): mean {filtered['mean']:.4f} m, "
              f"std {filtered['std']:.4f} m, median {filtered['median']:.4f} m, p95 {filtered['p95']:.4f} m")
    print(f"wrote {args.out / 'compare.json'}, {args.out / 'result.blend'}, {args.out / 'heat_map.png'} "
          f"in {time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    code = main(script_arguments())
    if code:
        sys.exit(code)
