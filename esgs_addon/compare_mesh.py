"""Measure imported Gaussians against a ground-truth mesh inside Blender.

Public entry point: :func:`compare_to_mesh`. The numbers come from
:func:`esgs.core.metrics.geometry.compare_points_to_mesh`; this module feeds it the objects'
geometry, stores each Gaussian's distance as the point attribute ``distance``, switches
the display to a blue -> red heat map (range adjustable on the modifier: ``Distance Min``
/ ``Distance Max``) and keeps the summary on the object for the panel.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional

import bpy
import numpy as np

from ..core.metrics.geometry import compare_points_to_mesh, load_mesh
from ..core.errors import ConfigError
from ..core.io_utils import atomic_write_json
from . import gaussian_nodes, gaussians_import

DISTANCE_ATTRIBUTE = "distance"
#: object custom property holding the last comparison's summary as JSON text
PROP_COMPARISON = "esgs_comparison"


def mesh_arrays(obj: bpy.types.Object, depsgraph: Optional[bpy.types.Depsgraph] = None) -> tuple[np.ndarray, np.ndarray]:
    """World-space vertices [V, 3] and triangles [F, 3] of a mesh object, modifiers applied."""
    if obj.type != "MESH":
        raise ConfigError(f"'{obj.name}' is a {obj.type.lower()}, not a mesh", hint="choose the ground-truth mesh")
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        vertices = np.zeros(len(mesh.vertices) * 3, dtype=np.float64)
        mesh.vertices.foreach_get("co", vertices)
        triangles = np.zeros(len(mesh.loop_triangles) * 3, dtype=np.int32)
        mesh.loop_triangles.foreach_get("vertices", triangles)
    finally:
        evaluated.to_mesh_clear()
    vertices = vertices.reshape(-1, 3)
    matrix = np.array(obj.matrix_world, dtype=np.float64)
    return vertices @ matrix[:3, :3].T + matrix[:3, 3], triangles.reshape(-1, 3).astype(np.int64)


def compare_to_mesh(gaussian_obj: bpy.types.Object, mesh_obj: bpy.types.Object | str | Path,
                    opacity_min: float = 0.5, threshold_m: float = 0.05, out_json: str | Path | None = None,
                    *, n_surface_samples: int = 100_000, seed: int = 0, show_heat_map: bool = True) -> dict[str, Any]:
    """Distances of the Gaussian centres to a mesh; returns the summary dict.

    Args:
        gaussian_obj: a point cloud from :func:`~.gaussians_import.import_gaussians`.
        mesh_obj: the ground-truth mesh object (compared in world space), or a mesh file
            (compared in the Gaussians' own frame, the frame of the PLY and the cameras).
        opacity_min: opacity filter of the filtered figures (recorded in the summary).
        threshold_m: match distance of precision / recall / F-score.
        out_json: write the summary there as JSON (atomically).
        n_surface_samples, seed: mesh sampling for completeness and recall.
        show_heat_map: switch the display to the distance heat map, blue at 0 and red at
            the 95th percentile of the filtered distances.

    The per-Gaussian distances are stored as the float point attribute ``distance``.

    Raises:
        ConfigError: the object is not a Gaussian point cloud or the mesh is not a mesh.
        DatasetError: the mesh has no triangles, or its file cannot be read.
    """
    if not gaussians_import.is_gaussian_object(gaussian_obj):
        raise ConfigError(f"'{getattr(gaussian_obj, 'name', gaussian_obj)}' is not an imported Gaussian point cloud",
                          hint="import a point_cloud.ply with ESGS > Import Gaussians first")
    arrays = gaussians_import.read_gaussian_arrays(gaussian_obj)
    points = arrays["position"].astype(np.float64)
    if isinstance(mesh_obj, (str, Path)):
        vertices, faces = load_mesh(mesh_obj)
        mesh_name, frame = str(mesh_obj), "gaussians_local"
    else:
        vertices, faces = mesh_arrays(mesh_obj)
        matrix = np.array(gaussian_obj.matrix_world, dtype=np.float64)
        points = points @ matrix[:3, :3].T + matrix[:3, 3]
        mesh_name, frame = mesh_obj.name, "world"
    result = compare_points_to_mesh(points, vertices, faces, opacities=arrays.get("opacity"), opacity_min=opacity_min,
                                    threshold_m=threshold_m, n_surface_samples=n_surface_samples, seed=seed)
    summary = dict(result.summary, gaussian_object=gaussian_obj.name, mesh=mesh_name, frame=frame,
                   gaussians_file=gaussian_obj.get(gaussians_import.PROP_SOURCE, ""))

    attributes = gaussian_obj.data.attributes
    existing = attributes.get(DISTANCE_ATTRIBUTE)
    if existing is not None:
        attributes.remove(existing)
    attribute = attributes.new(DISTANCE_ATTRIBUTE, "FLOAT", "POINT")
    attribute.data.foreach_set("value", result.distances.astype(np.float32))
    gaussian_obj[PROP_COMPARISON] = json.dumps(summary)
    if out_json:
        atomic_write_json(out_json, summary)
    if show_heat_map and gaussian_nodes.MODIFIER_NAME in gaussian_obj.modifiers:
        p95 = summary["gaussians_to_mesh_filtered"]["p95"] or summary["gaussians_to_mesh"]["p95"] or threshold_m
        gaussian_nodes.set_display_inputs(gaussian_obj, heat_map=True, distance_min=0.0,
                                          distance_max=float(max(p95, 1e-9)))
    gaussian_obj.data.update_tag()
    return summary


def last_comparison(obj: Optional[bpy.types.Object]) -> Optional[dict[str, Any]]:
    """The summary stored by the last :func:`compare_to_mesh` on ``obj``, or None."""
    if obj is None or PROP_COMPARISON not in obj:
        return None
    try:
        return json.loads(obj[PROP_COMPARISON])
    except (TypeError, ValueError):
        return None
