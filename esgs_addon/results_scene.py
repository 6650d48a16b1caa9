"""A .blend of a finished run: cameras, ground-truth mesh, Gaussians with the distance heat map.

``build_results_blend(scene_dir, run_dir, out_dir)`` is what the demo (and a user after
training) calls; ``python -m esgs.esgs_addon.results_scene --scene S --run R --out O`` runs
it headless with the bpy module; the demo runs :func:`child_job`, the ``"results_scene"`` job of
the child-process runtime (:mod:`esgs.core.runtime`), since core never imports bpy.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import bpy

from ..core.errors import DatasetError, ESGSError
from ..core.formats.scene_dir import SceneDir
from ..core.formats.run_dir import RunDir
from . import compare_mesh, gaussian_nodes
from .colmap_scene import ColmapImportOptions, import_colmap_scene
from .gaussians_import import import_gaussians


def _import_ground_truth(mesh_path: Path, collection: bpy.types.Collection) -> bpy.types.Object:
    """The ground-truth PLY as a mesh object (vertex/face arrays through foreach_set)."""
    import trimesh

    mesh = trimesh.load(mesh_path, force="mesh", process=False)
    data = bpy.data.meshes.new("ground_truth")
    data.vertices.add(len(mesh.vertices))
    data.vertices.foreach_set("co", mesh.vertices.astype("float32").ravel())
    faces = mesh.faces.astype("int32")
    data.loops.add(faces.size)
    data.loops.foreach_set("vertex_index", faces.ravel())
    data.polygons.add(len(faces))
    data.polygons.foreach_set("loop_start", (3 * __import__("numpy").arange(len(faces))).astype("int32"))
    data.update()
    obj = bpy.data.objects.new("ground_truth", data)
    material = bpy.data.materials.new("ground_truth_grey")
    material.diffuse_color = (0.55, 0.55, 0.55, 1.0)
    data.materials.append(material)
    collection.objects.link(obj)
    return obj


def render_picture(camera: bpy.types.Object, path: Path, width: int = 480, height: int = 270, samples: int = 16) -> Path:
    """Render the current scene from ``camera`` with Cycles on the CPU into a PNG."""
    scene = bpy.context.scene
    scene.camera = camera
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(path)
    if scene.world is None:
        scene.world = bpy.data.worlds.new("World")
    bpy.ops.render.render(write_still=True)
    return path


def build_results_blend(scene_dir: str | Path, run_dir: str | Path, out_dir: str | Path, *, opacity_min: float = 0.5,
                        threshold_m: float = 0.05, picture_size: tuple[int, int] = (480, 270)) -> dict[str, Any]:
    """Import a run next to its scene's ground truth, compare, save ``results.blend`` and a heat-map PNG.

    Returns the comparison summary plus the written paths. Raises :class:`DatasetError` when
    the scene has no ground-truth mesh or the run no point cloud.
    """
    scene_dir, run_dir, out_dir = Path(scene_dir), Path(run_dir), Path(out_dir)
    mesh_path = SceneDir(scene_dir).ground_truth_mesh
    ply_path = RunDir(run_dir).point_cloud
    if not mesh_path.is_file():
        raise DatasetError("the scene has no ground-truth mesh", path=mesh_path, hint="make one with esgs scene")
    if not ply_path.is_file():
        raise DatasetError("the run has no point_cloud.ply", path=ply_path, hint="train first (esgs train)")
    out_dir.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    from .. import register

    register()
    imported = import_colmap_scene(scene_dir, ColmapImportOptions(import_points=False))
    collection = imported["collection"]
    ground_truth = _import_ground_truth(mesh_path, collection)
    gaussians = import_gaussians(ply_path, name="gaussians", collection=collection)
    summary = compare_mesh.compare_to_mesh(gaussians, ground_truth, opacity_min=opacity_min, threshold_m=threshold_m,
                                           out_json=out_dir / "compare.json")
    gaussian_nodes.set_display_inputs(gaussians, opacity_min=0.05)
    blend_path = out_dir / "results.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend_path))
    ground_truth.hide_render = True
    picture = render_picture(imported["cameras"][0], out_dir / "heat_map.png", *picture_size)
    return {**summary, "blend": str(blend_path), "heat_map": str(picture)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m esgs.esgs_addon.results_scene", description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--run", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--opacity-min", type=float, default=0.5)
    parser.add_argument("--threshold", type=float, default=0.05, help="match distance in scene units")
    args = parser.parse_args(argv)
    try:
        summary = build_results_blend(args.scene, args.run, args.out, opacity_min=args.opacity_min,
                                      threshold_m=args.threshold)
    except ESGSError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(json.dumps({k: summary[k] for k in ("blend", "heat_map", "precision", "recall", "fscore")}))
    return 0


def child_job(data: dict, context: Any) -> dict:
    """The ``"results_scene"`` job of the child-process runtime (the demo's Blender stage):
    ``data`` holds ``scene``, ``run``, ``out`` and optionally ``opacity_min``, ``threshold_m``;
    returns the .blend and heat-map paths and the comparison's precision, recall and F-score."""
    summary = build_results_blend(Path(data["scene"]), Path(data["run"]), Path(data["out"]),
                                  opacity_min=float(data.get("opacity_min", 0.5)),
                                  threshold_m=float(data.get("threshold_m", 0.05)))
    return {k: summary[k] for k in ("blend", "heat_map", "precision", "recall", "fscore")}


if __name__ == "__main__":
    sys.exit(main())
