"""Depth and normal labels of a COLMAP scene, rendered from a mesh with Cycles.

Public entry point: :func:`render_labels`. For every image of ``SCENE/sparse/0`` it places
a Blender camera with the exact intrinsics and pose of the model (the COLMAP import of
:mod:`.colmap_scene`), renders the mesh's Depth and Normal passes with Cycles on the CPU,
fills the holes (:mod:`esgs.core.labels.fill`) and writes ``SCENE/priors/labels/`` in the
standard prior format, atomically (:class:`esgs.core.labels.writer.LabelWriter`).

Everything happens in a temporary Blender scene holding only the imported cameras and the
mesh; it and every datablock it used are removed afterwards (also on failure), so the
user's file is left as it was and no other object can show up in the labels.

Headless: ``python -m esgs.esgs_addon.render_labels SCENE --mesh MESH [--method mesh]``.
``esgs labels`` runs :func:`child_job`, the ``"render_labels"`` job of the child-process
runtime (:mod:`esgs.core.runtime`).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import bpy
import numpy as np

from ..core.errors import ConfigError, DatasetError, ESGSError
from ..core.labels.fill import FillOptions
from ..core.progress import ProgressEvent

#: Cycles samples per pixel of a label render. Cycles' Depth pass holds the first sample's
#: depth (its position set by the seed and the pixel filter, which we leave at Blender's
#: defaults as the synthetic scenes do); one sample gave the same depth as the scene's 8
#: (checked: median relative difference 7e-8 on cratered_plain). More samples only
#: average the Normal pass over the pixel's footprint.
DEFAULT_SAMPLES = 1


def _label_render_settings(scene: bpy.types.Scene, samples: int) -> None:
    """Cycles on the CPU, no denoising and no light bounces: only the data passes matter."""
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(samples)
    scene.cycles.use_adaptive_sampling = True
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 0
    scene.render.use_persistent_data = True  # one BVH for all views
    scene.render.image_settings.media_type = "IMAGE"
    scene.render.image_settings.file_format = "PNG"


def _mesh_object(vertices: np.ndarray, triangles: np.ndarray, scene: bpy.types.Scene, smooth: bool) -> bpy.types.Object:
    from .terrain_scene import mesh_from_arrays

    mesh = mesh_from_arrays("ESGS label mesh", vertices, triangles.astype(np.int32), smooth=smooth)
    obj = bpy.data.objects.new("ESGS label mesh", mesh)
    scene.collection.objects.link(obj)
    return obj


def render_labels(scene_dir: str | Path, mesh_path: str | Path, *, method: str = "mesh",
                  fill: FillOptions | None = None, smooth: bool = True, samples: int = 0,
                  metadata: dict[str, Any] | None = None, gaps_path: str | Path | None = None,
                  progress: Callable[[ProgressEvent], None] | None = None) -> dict[str, Any]:
    """Render depth/normal labels of every image of ``scene_dir`` from ``mesh_path``.

    method: how the mesh was obtained, recorded in the metadata (``mesh`` = given by the
    user, ``reconstruct`` = :func:`esgs.core.labels.reconstruct_mesh`). smooth: shade with
    interpolated vertex normals (terrain) or flat faces. samples: Cycles samples (0 =
    :data:`DEFAULT_SAMPLES`). gaps_path: the gap mesh of a reconstructed mesh
    (:mod:`esgs.core.labels.gaps`); labels seen through one of its triangles are dropped.
    Returns the ``labels.json`` report (a dict).
    Raises :class:`DatasetError` / :class:`ConfigError` before rendering for a missing
    mesh, a scene without a COLMAP model or without images; nothing is written then.
    """
    from ..core.colmap.io import read_model
    from ..core.labels.gaps import through_gap, zbuffer_depth
    from ..core.labels.mesh_io import load_mesh
    from ..core.labels.pipeline import check_pinhole
    from ..core.labels.writer import LabelWriter
    from ..core.formats.scene_dir import PriorSource, SceneDir
    from .cameras import opencv_from_camera_object, use_camera
    from .colmap_scene import PROP_IMAGE_NAME, ColmapImportOptions, import_colmap_scene
    from .render_dataset import _PassOutputs, _read_single_channel, _read_vector, camera_normals_from_pass, depth_from_pass

    scene_dir = Path(scene_dir)
    report = progress or (lambda event: None)
    if samples < 0:
        raise ConfigError(f"samples must be >= 0 (0 = the scene's), got {samples}")
    model = read_model(scene_dir)  # DatasetError when there is no model
    if not model.images:
        raise DatasetError("the COLMAP model has no images (no cameras to render)", path=scene_dir,
                           hint="run SfM first (esgs dataset from-images) so every image has a pose")
    check_pinhole(model, scene_dir)
    vertices, triangles = load_mesh(mesh_path)
    gap_vertices, gap_triangles = load_mesh(gaps_path) if gaps_path is not None else (None, None)
    samples = samples or DEFAULT_SAMPLES
    metadata = {"method": method, "mesh": str(Path(mesh_path).resolve()), "renderer": "Cycles CPU, Depth and Normal passes",
                "samples": samples, "shading": "smooth" if smooth else "flat", **(metadata or {})}
    if gaps_path is not None:
        metadata["gap_mesh"] = str(Path(gaps_path).resolve())
        metadata["gap_rule"] = "labels behind a gap triangle on their ray (beyond 1 %) are dropped"

    before = {name: {block.session_uid for block in getattr(bpy.data, name)}
              for name in ("scenes", "objects", "meshes", "cameras", "collections", "node_groups", "images")}
    label_scene = bpy.data.scenes.new("ESGS labels")
    start = time.perf_counter()
    try:
        _label_render_settings(label_scene, samples)
        imported = import_colmap_scene(scene_dir, ColmapImportOptions(import_points=False, set_scene_resolution=True),
                                       scene=label_scene)
        cameras = imported["cameras"]
        _mesh_object(vertices, triangles, label_scene, smooth)
        total = len(cameras)
        with tempfile.TemporaryDirectory(prefix="esgs_labels_") as scratch, \
                LabelWriter(scene_dir, metadata, fill) as writer:
            passes = _PassOutputs(label_scene, Path(scratch))
            try:
                for index, camera in enumerate(cameras):
                    view_start = time.perf_counter()
                    name = str(camera[PROP_IMAGE_NAME])
                    use_camera(label_scene, camera)
                    K, world_to_camera, _, _ = opencv_from_camera_object(camera, label_scene)
                    pass_files = passes.set_prefix(f"view{index:05d}_")
                    label_scene.render.filepath = str(Path(scratch) / f"view{index:05d}.png")
                    bpy.ops.render.render(write_still=False, scene=label_scene.name)
                    for pass_name, path in pass_files.items():
                        if not path.is_file():
                            raise DatasetError(f"Cycles did not write the {pass_name} pass", path=path)
                    depth = depth_from_pass(_read_single_channel(pass_files["Depth"]))
                    normal = camera_normals_from_pass(_read_vector(pass_files["Normal"]), world_to_camera, depth > 0)
                    for path in pass_files.values():
                        path.unlink()
                    exclude = None
                    if gap_triangles is not None:
                        gap_depth = zbuffer_depth(gap_vertices, gap_triangles, K, world_to_camera, depth.shape[1], depth.shape[0])
                        exclude = through_gap(depth, gap_depth)
                    stats = writer.add(name, depth, normal, exclude)
                    report(ProgressEvent(index + 1, total, "labels", message=f"labels of {name}", metrics={
                        "view_s": time.perf_counter() - view_start, "rendered": stats["rendered_fraction"],
                        "filled": stats["filled_fraction"]}))
            finally:
                passes.close()
    finally:
        created = [block for name, uids in before.items() for block in getattr(bpy.data, name)
                   if block.session_uid not in uids]
        if created:
            bpy.data.batch_remove(created)
    result = json.loads(SceneDir(scene_dir).labels_report.read_text())
    report(ProgressEvent(total, total, "labels", kind="done", message=f"labels written: {SceneDir(scene_dir).prior(PriorSource.LABELS)}",
                         metrics={"seconds": time.perf_counter() - start}))
    return result


# ----------------------------------------------------------------------------- child process


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="render_labels", description="render depth/normal labels from a mesh")
    parser.add_argument("scene", type=Path)
    parser.add_argument("--mesh", type=Path, required=True)
    parser.add_argument("--method", default="mesh")
    parser.add_argument("--gaps", type=Path, default=None, help="gap mesh of a reconstructed mesh")
    parser.add_argument("--samples", type=int, default=0, help="Cycles samples (0 = 1)")
    parser.add_argument("--flat", action="store_true")
    parser.add_argument("--max-hole-fraction", type=float, default=FillOptions.max_hole_fraction)
    parser.add_argument("--edge-radius-px", type=int, default=FillOptions.edge_radius_px)
    parser.add_argument("--metadata", default="{}", help="JSON object of extra metadata strings")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m esgs.esgs_addon.render_labels`` (see the module docstring)."""
    from ..core.progress import ConsoleProgress

    args = build_parser().parse_args(argv)
    console = ConsoleProgress()
    try:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        render_labels(args.scene, args.mesh, method=args.method, samples=args.samples, smooth=not args.flat,
                      fill=FillOptions(max_hole_fraction=args.max_hole_fraction, edge_radius_px=args.edge_radius_px),
                      metadata=json.loads(args.metadata), gaps_path=args.gaps, progress=console)
    except ESGSError as error:
        print(f"render_labels: error: {error}", file=sys.stderr)
        return 2
    finally:
        console.close()
    return 0


def child_job(data: dict[str, Any], context: Any) -> dict[str, Any]:
    """The ``"render_labels"`` job of the child-process runtime: ``data`` holds
    :func:`render_labels`' arguments (``scene``, ``mesh``, ``method``, ``samples``, ``smooth``,
    ``fill`` as a FillOptions dict, ``metadata``, ``gaps``) in a fresh Blender file."""
    from ..core.config import config_from_dict

    bpy.ops.wm.read_factory_settings(use_empty=True)
    fill = config_from_dict(FillOptions, data.get("fill") or {}, source=context.config_path)
    return render_labels(data["scene"], data["mesh"], method=data.get("method", "mesh"),
                         samples=int(data.get("samples", 0)), smooth=bool(data.get("smooth", True)), fill=fill,
                         metadata=dict(data.get("metadata") or {}), gaps_path=data.get("gaps"),
                         progress=context.progress)


if __name__ == "__main__":
    sys.exit(main())
