"""Measure imported Gaussians against a ground-truth mesh inside Blender.

Public entry point: :func:`compare_to_mesh`. The numbers come from
:func:`esgs.core.metrics.geometry.compare_points_to_mesh`; this module feeds it the objects'
geometry and the training cameras of the run the Gaussians come from (:func:`training_cameras`:
recall then counts only the surface they saw), stores each Gaussian's distance as the point
attribute ``distance``, switches the display to a blue -> red heat map (range adjustable on
the modifier: ``Distance Min`` / ``Distance Max``) with its colour legend in metres beside
the point cloud (:func:`make_legend`), and keeps the summary on the object for the panel.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import bpy
import numpy as np
from mathutils import Vector

from ..core.metrics.geometry import compare_points_to_mesh, load_mesh
from ..core.metrics.visibility import CameraView, cameras_from_colmap, training_image_names
from ..core.errors import ConfigError, ESGSError
from ..core.io_utils import atomic_write_json
from . import gaussian_nodes, gaussians_import

DISTANCE_ATTRIBUTE = "distance"
#: object custom property holding the last comparison's summary as JSON text
PROP_COMPARISON = "esgs_comparison"
#: what :func:`~.training_job.import_run_result` stores on the object: the run folder
PROP_RUN_DIR = "esgs_run_dir"
#: on the legend's objects: the name of the Gaussian object whose heat map they explain
PROP_LEGEND_OF = "esgs_legend_of"
#: on the legend's colour bar: the distances (metres) at its two ends
PROP_LEGEND_MIN, PROP_LEGEND_MAX = "esgs_legend_min", "esgs_legend_max"
LEGEND_COLOUR_ATTRIBUTE = "legend_colour"
#: the training split of a run whose config.json does not say (TrainConfig's default)
DEFAULT_TEST_EVERY = 8


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


def training_cameras(gaussian_obj: bpy.types.Object,
                     world_from_model: Optional[np.ndarray] = None) -> tuple[Optional[list[CameraView]], str]:
    """The training cameras of the run ``gaussian_obj`` was imported from, and where they came from.

    The run folder (object property ``esgs_run_dir``) names its scene folder and its split in
    ``config.json``; without one, the scene folder of the object's collection (a COLMAP
    import) with the trainer's default split. ``world_from_model`` places the COLMAP frame
    in the comparison's frame (None: the Gaussians' own frame).

    Returns:
        (cameras, description); cameras is None, and the description says why, when no
        scene folder or COLMAP model can be found.
    """
    from ..core.colmap.io import find_model_dir, read_model
    from ..core.formats.run_dir import RunDir
    from . import training_job

    scene_dir, test_every = None, DEFAULT_TEST_EVERY
    run_dir = gaussian_obj.get(PROP_RUN_DIR)
    if run_dir:
        config_path = RunDir(Path(run_dir)).config
        try:
            config = json.loads(config_path.read_text())
        except (OSError, ValueError):
            config = {}
        if config.get("scene"):
            scene_dir = Path(config["scene"])
            test_every = int(config.get("test_every", DEFAULT_TEST_EVERY))
    if scene_dir is None:
        for collection in gaussian_obj.users_collection:
            scene_dir = training_job.scene_dir_of_collection(collection)
            if scene_dir is not None:
                break
    if scene_dir is None:
        return None, "no training cameras known (not imported from a run or a COLMAP scene)"
    try:
        model = read_model(find_model_dir(scene_dir)[0])
    except (ESGSError, OSError) as error:
        return None, f"no training cameras: cannot read the COLMAP model of {scene_dir} ({error})"
    names = training_image_names([image.name for image in model.images.values()], test_every)
    cameras = cameras_from_colmap(model, names, world_from_model=world_from_model)
    return cameras, f"{len(cameras)} training views of {scene_dir.name} (of {len(model.images)} images)"


def compare_to_mesh(gaussian_obj: bpy.types.Object, mesh_obj: bpy.types.Object | str | Path,
                    opacity_min: float = 0.5, threshold_m: Optional[float] = None,
                    out_json: str | Path | None = None, *, n_surface_samples: int = 100_000, seed: int = 0,
                    show_heat_map: bool = True,
                    cameras: Union[str, Sequence[CameraView], None] = "training") -> dict[str, Any]:
    """Distances of the Gaussian centres to a mesh; returns the summary dict.

    Args:
        gaussian_obj: a point cloud from :func:`~.gaussians_import.import_gaussians`.
        mesh_obj: the ground-truth mesh object (compared in world space), or a mesh file
            (compared in the Gaussians' own frame, the frame of the PLY and the cameras).
        opacity_min: opacity filter of the filtered figures (recorded in the summary).
        threshold_m: match distance of precision / recall / F-score; None: scaled to the
            scene (1 % of the median camera-to-surface distance, see
            :func:`esgs.core.metrics.visibility.scene_threshold`).
        out_json: write the summary there as JSON (atomically).
        n_surface_samples, seed: mesh sampling for completeness and recall.
        show_heat_map: switch the display to the distance heat map, blue at 0 and red at
            the 95th percentile of the filtered distances, and add its legend in metres.
        cameras: ``"training"``: the training cameras of the Gaussians' run
            (:func:`training_cameras`); recall and completeness then count only the mesh
            surface they saw. A list of :class:`~esgs.core.metrics.visibility.CameraView`
            in the comparison's frame: those. None: the whole mesh counts.

    The per-Gaussian distances are stored as the float point attribute ``distance``. The
    summary records ``cameras`` (where the cameras came from), ``visible_fraction`` and
    ``threshold_m`` / ``threshold_rule``.

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
        mesh_name, frame, world_from_model = str(mesh_obj), "gaussians_local", None
    else:
        vertices, faces = mesh_arrays(mesh_obj)
        matrix = np.array(gaussian_obj.matrix_world, dtype=np.float64)
        points = points @ matrix[:3, :3].T + matrix[:3, 3]
        mesh_name, frame, world_from_model = mesh_obj.name, "world", matrix
    if isinstance(cameras, str):
        if cameras != "training":
            raise ConfigError(f"cameras must be 'training', a list of camera views or None, not {cameras!r}")
        views, cameras_source = training_cameras(gaussian_obj, world_from_model)
    elif cameras is None:
        views, cameras_source = None, "none: recall over the whole mesh"
    else:
        views, cameras_source = list(cameras), f"{len(cameras)} given views"
    result = compare_points_to_mesh(points, vertices, faces, opacities=arrays.get("opacity"), opacity_min=opacity_min,
                                    threshold_m=threshold_m, n_surface_samples=n_surface_samples, seed=seed,
                                    cameras=views)
    summary = dict(result.summary, gaussian_object=gaussian_obj.name, mesh=mesh_name, frame=frame,
                   gaussians_file=gaussian_obj.get(gaussians_import.PROP_SOURCE, ""), cameras=cameras_source)

    attributes = gaussian_obj.data.attributes
    existing = attributes.get(DISTANCE_ATTRIBUTE)
    if existing is not None:
        attributes.remove(existing)
    attribute = attributes.new(DISTANCE_ATTRIBUTE, "FLOAT", "POINT")
    attribute.data.foreach_set("value", result.distances.astype(np.float32))
    if show_heat_map and gaussian_nodes.MODIFIER_NAME in gaussian_obj.modifiers:
        p95 = summary["gaussians_to_mesh_filtered"]["p95"] or summary["gaussians_to_mesh"]["p95"] \
            or summary["threshold_m"]
        distance_max = float(max(p95, 1e-9))
        gaussian_nodes.set_display_inputs(gaussian_obj, heat_map=True, distance_min=0.0, distance_max=distance_max)
        legend = make_legend(gaussian_obj, 0.0, distance_max, points=points)
        summary["legend"] = legend.name
    gaussian_obj[PROP_COMPARISON] = json.dumps(summary)
    if out_json:
        atomic_write_json(out_json, summary)
    gaussian_obj.data.update_tag()
    return summary


def describe(summary: dict[str, Any]) -> str:
    """One sentence for a report: F-score, threshold in metres and its rule, recall's scope."""
    if summary.get("fscore") is None:
        return (f"no Gaussian has opacity >= {summary.get('opacity_min') or 0:g}, so precision, recall and F-score "
                f"are undefined: lower the opacity filter (of {summary.get('n_gaussians', 0):,} Gaussians)")
    text = (f"F-score {summary['fscore']:.3f} (precision {summary['precision']:.3f}, recall {summary['recall']:.3f}) "
            f"at {summary['threshold_m']:.4g} m")
    if summary.get("threshold_rule") and summary["threshold_rule"] != "given":
        text += f" ({summary['threshold_rule']})"
    if summary.get("n_visible_samples") is not None:
        text += (f"; recall over the {summary['visible_fraction']:.0%} of the mesh the training cameras saw "
                 f"({summary['n_visible_samples']:,} of {summary['n_surface_samples']:,} samples, "
                 f"{summary.get('n_cameras', 0)} cameras)")
    else:
        text += "; recall over the whole mesh (no training cameras known)"
    return text


# --------------------------------------------------------------------------- legend


def legend_objects(gaussian_obj: bpy.types.Object) -> list[bpy.types.Object]:
    """The legend objects (colour bar first, then its labels) of ``gaussian_obj``'s heat map."""
    found = [obj for obj in bpy.data.objects if obj.get(PROP_LEGEND_OF) == gaussian_obj.name]
    return sorted(found, key=lambda obj: (obj.type != "MESH", obj.name))


def make_legend(gaussian_obj: bpy.types.Object, distance_min: float, distance_max: float, *,
                points: Optional[np.ndarray] = None) -> bpy.types.Object:
    """The heat map's colour legend beside the point cloud: a colour bar and its labels in metres.

    A flat bar (the heat map's colours, blue at ``distance_min`` to red at ``distance_max``,
    as a colour attribute shown by its material and by Solid shading's Attribute colour),
    lying under the cloud's bounding box (``points`` [N, 3] world, default: the object's
    bounding box), with text objects ``"<min> m"``, ``"<max> m"`` and a title, parented to
    the Gaussian object and in its collection. A previous legend of the object is replaced.

    Returns the colour bar object (``esgs_legend_min`` / ``esgs_legend_max`` hold its range).
    """
    for old in legend_objects(gaussian_obj):
        data = old.data
        bpy.data.objects.remove(old, do_unlink=True)
        if data is not None and data.users == 0:
            (bpy.data.meshes if isinstance(data, bpy.types.Mesh) else bpy.data.curves).remove(data)
    if points is None or len(points) == 0:
        corners = np.array([gaussian_obj.matrix_world @ Vector(c)
                            for c in gaussian_obj.bound_box])
    else:
        corners = np.asarray(points, dtype=np.float64)
    low, high = corners.min(axis=0), corners.max(axis=0)
    width = max(float(max(high[0] - low[0], high[1] - low[1])) * 0.4, 1e-3)
    height = width / 8.0
    origin = np.array([low[0], low[1] - 2.5 * height, high[2]])
    collection = gaussian_obj.users_collection[0] if gaussian_obj.users_collection else bpy.context.scene.collection
    name = f"{gaussian_obj.name} legend"

    from .gaussian_nodes import HEAT_COLOURS

    stops = [position for position, _ in HEAT_COLOURS]
    vertices = [(origin[0] + width * t, origin[1] + dy, origin[2]) for t in stops for dy in (0.0, height)]
    faces = [(2 * i, 2 * i + 2, 2 * i + 3, 2 * i + 1) for i in range(len(stops) - 1)]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(vertices, [], faces)
    colours = mesh.color_attributes.new(LEGEND_COLOUR_ATTRIBUTE, "FLOAT_COLOR", "POINT")
    colours.data.foreach_set("color", np.repeat([rgba for _, rgba in HEAT_COLOURS], 2, axis=0).ravel())
    mesh.color_attributes.active_color = colours
    mesh.materials.append(_legend_material())
    bar = bpy.data.objects.new(name, mesh)
    collection.objects.link(bar)
    labels = ((f"{distance_min:.3g} m", origin[0]), (f"{distance_max:.3g} m", origin[0] + width),
              ("distance to mesh", origin[0] + width / 2))
    text_objects = []
    for index, (text, x) in enumerate(labels):
        curve = bpy.data.curves.new(f"{name} {('min', 'max', 'title')[index]}", "FONT")
        curve.body = text
        curve.size = height * 0.9
        curve.align_x = ("LEFT", "RIGHT", "CENTER")[index]
        label = bpy.data.objects.new(curve.name, curve)
        label.location = (x, origin[1] - height * 1.1 if index < 2 else origin[1] + height * 1.3, origin[2])
        collection.objects.link(label)
        text_objects.append(label)
    inverse = gaussian_obj.matrix_world.inverted_safe()
    for obj in [bar] + text_objects:
        obj[PROP_LEGEND_OF] = gaussian_obj.name
        obj.parent = gaussian_obj
        obj.matrix_parent_inverse = inverse  # stays where it was put, then follows the cloud
    bar[PROP_LEGEND_MIN], bar[PROP_LEGEND_MAX] = float(distance_min), float(distance_max)
    return bar


def _legend_material() -> bpy.types.Material:
    """Emission of the bar's colour attribute: the heat map's colours whatever the lighting."""
    material = bpy.data.materials.get("ESGS Heat Map Legend")
    if material is not None:
        return material
    material = bpy.data.materials.new("ESGS Heat Map Legend")
    if material.node_tree is None:  # Blender < 5 made node-less materials by default
        material.use_nodes = True
    nodes, links = material.node_tree.nodes, material.node_tree.links
    nodes.clear()
    attribute = nodes.new("ShaderNodeAttribute")
    attribute.attribute_name = LEGEND_COLOUR_ATTRIBUTE
    emission = nodes.new("ShaderNodeEmission")
    output = nodes.new("ShaderNodeOutputMaterial")
    links.new(attribute.outputs["Color"], emission.inputs["Color"])
    links.new(emission.outputs["Emission"], output.inputs["Surface"])
    return material


def last_comparison(obj: Optional[bpy.types.Object]) -> Optional[dict[str, Any]]:
    """The summary stored by the last :func:`compare_to_mesh` on ``obj``, or None."""
    if obj is None or PROP_COMPARISON not in obj:
        return None
    try:
        return json.loads(obj[PROP_COMPARISON])
    except (TypeError, ValueError):
        return None
