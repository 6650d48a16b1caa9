"""Build a renderable scene in Blender from an external textured mesh (.glb/.gltf/.obj/.ply).

Public entry point: :func:`build_mesh_scene`. It imports the mesh with Blender's own
importer (glTF's +Y up becomes Blender's +Z up), then, in one new collection:

* joins every imported mesh object into one object ``ESGS mesh terrain`` whose vertices are
  already in world space (identity transform), merges vertices that coincide (tile borders
  of the Mars landform), drops custom and sharp-edge normals and shades it smooth, so
  Cycles' shading normal is exactly Blender's vertex normal, as the ground-truth export
  (:func:`~.render_dataset.world_mesh_arrays`) writes it;
* turns every material into its observed appearance: the base colour (texture) feeds an
  Emission shader of strength 1, the world is black (a Mars sky gradient for the ``mixed``
  rig, whose rover views see the sky; it does not light emission) and there are no lamps, so with the
  Standard view transform a pixel shows the photograph's value (the landform's textures
  are photographs with the light already in them);
* places the cameras of :func:`esgs.core.terrain.mesh_scene.make_mesh_rig`, ray casting the mesh
  with a BVH tree.

The returned dict has the keys :func:`~.render_dataset.render_dataset` reads, so the scene
folder is exactly the synthetic presets' one (docs/mesh_scenes.md).
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any, Callable

import bpy
import numpy as np

from ..core.config import config_to_dict
from ..core.errors import DatasetError
from ..core.terrain.mesh_scene import MeshSceneConfig, check_mesh_file, make_mesh_rig
from ..core.progress import ProgressEvent

GENERATOR_VERSION = "1.0"
PROP_ROLE = "esgs_role"
_DATA_KINDS = ("objects", "meshes", "materials", "images", "cameras", "lights", "collections", "worlds", "node_groups")
#: Normal-related attributes that would make Cycles shade with corner normals instead of vertex normals.
_NORMAL_ATTRIBUTES = ("custom_normal", "sharp_edge", "sharp_face")


class _NewData:
    """Datablocks that appeared since construction, so a failure can remove all of them."""

    def __init__(self) -> None:
        self.before = {kind: {block.as_pointer() for block in getattr(bpy.data, kind)} for kind in _DATA_KINDS}

    def new(self, kind: str) -> list[Any]:
        return [block for block in getattr(bpy.data, kind) if block.as_pointer() not in self.before[kind]]

    def remove_all(self) -> None:
        for kind in _DATA_KINDS:
            for block in self.new(kind):
                try:
                    getattr(bpy.data, kind).remove(block)
                except (ReferenceError, RuntimeError):
                    pass


def import_mesh_file(path: Path) -> list[bpy.types.Object]:
    """Import ``path`` with Blender's importer for its type; returns the new objects.

    Raises :class:`DatasetError` naming the file when the importer fails.
    """
    suffix = path.suffix.lower()
    before = {obj.as_pointer() for obj in bpy.data.objects}
    try:
        if suffix in (".glb", ".gltf"):
            result = bpy.ops.import_scene.gltf(filepath=str(path))
        elif suffix == ".obj":
            result = bpy.ops.wm.obj_import(filepath=str(path))
        elif suffix == ".ply":
            result = bpy.ops.wm.ply_import(filepath=str(path))
        else:
            raise DatasetError(f"unsupported mesh file type {suffix!r}", path=path)
    except RuntimeError as error:
        raise DatasetError(f"Blender could not read the mesh: {str(error).strip().splitlines()[-1]}", path=path,
                           hint="check that the file is a valid, complete mesh file") from error
    if "FINISHED" not in result:
        raise DatasetError("Blender could not read the mesh (the importer was cancelled)", path=path)
    return [obj for obj in bpy.data.objects if obj.as_pointer() not in before]


def _bake_and_join(objects: list[bpy.types.Object], collection: bpy.types.Collection) -> bpy.types.Object:
    """One mesh object in ``collection`` holding all ``objects`` with their world transforms applied."""
    meshes = [obj for obj in objects if obj.type == "MESH"]
    for obj in meshes:
        matrix = obj.matrix_world.copy()
        if obj.data.users > 1:
            obj.data = obj.data.copy()
        obj.parent = None
        obj.data.transform(matrix)
        obj.matrix_world.identity()
    for obj in objects:
        for owner in list(obj.users_collection):
            owner.objects.unlink(obj)
        if obj.type == "MESH":
            collection.objects.link(obj)
        else:
            bpy.data.objects.remove(obj)
    target = meshes[0]
    if len(meshes) > 1:
        with bpy.context.temp_override(active_object=target, object=target, selected_objects=meshes,
                                       selected_editable_objects=meshes):
            bpy.ops.object.join()
    target.name = "ESGS mesh terrain"
    return target


def clean_mesh(mesh: bpy.types.Mesh, merge_distance: float = 0.0) -> None:
    """Merge vertices closer than ``merge_distance`` (0 = identical positions), drop the faces
    that collapse, drop custom and sharp normals, shade smooth."""
    import bmesh

    for name in _NORMAL_ATTRIBUTES:
        attribute = mesh.attributes.get(name)
        if attribute is not None:
            mesh.attributes.remove(attribute)
    bm = bmesh.new()
    try:
        bm.from_mesh(mesh)
        bmesh.ops.remove_doubles(bm, verts=bm.verts[:], dist=merge_distance)
        bm.to_mesh(mesh)
    finally:
        bm.free()
    for name in _NORMAL_ATTRIBUTES:
        attribute = mesh.attributes.get(name)
        if attribute is not None:
            mesh.attributes.remove(attribute)
    mesh.shade_smooth()
    mesh.update()


def make_emission_material(material: bpy.types.Material) -> None:
    """Rewire ``material`` so its base colour (texture or value) is emitted unlit at strength 1.

    The colour source is the socket feeding a Principled BSDF's Base Color, else the first
    image texture's Color, else the material's viewport colour.
    """
    if material.node_tree is None:  # materials of older files; Blender 5 gives every new one a tree
        material.use_nodes = True
    tree = material.node_tree
    source = None
    default = tuple(material.diffuse_color)
    for node in tree.nodes:
        if node.type == "BSDF_PRINCIPLED":
            base = node.inputs["Base Color"]
            if base.is_linked:
                source = base.links[0].from_socket
            else:
                default = tuple(base.default_value)
            break
    if source is None:
        textures = [node for node in tree.nodes if node.type == "TEX_IMAGE" and node.image is not None]
        if textures:
            source = textures[0].outputs["Color"]
    output = next((node for node in tree.nodes if node.type == "OUTPUT_MATERIAL" and node.is_active_output), None)
    if output is None:
        output = tree.nodes.new("ShaderNodeOutputMaterial")
    emission = tree.nodes.new("ShaderNodeEmission")
    emission.name = emission.label = "ESGS observed appearance"
    emission.inputs["Strength"].default_value = 1.0
    if source is not None:
        tree.links.new(source, emission.inputs["Color"])
    else:
        emission.inputs["Color"].default_value = default
    for link in list(output.inputs["Surface"].links):
        tree.links.remove(link)
    tree.links.new(emission.outputs["Emission"], output.inputs["Surface"])
    for link in list(output.inputs["Displacement"].links):
        tree.links.remove(link)  # the ground truth is the undisplaced mesh


def bvh_ray_caster(vertices: np.ndarray, triangles: np.ndarray) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``cast(origins [N, 3], directions [N, 3]) -> distances [N]`` (inf on a miss) on a triangle mesh."""
    from mathutils import Vector
    from mathutils.bvhtree import BVHTree

    tree = BVHTree.FromPolygons(np.asarray(vertices, dtype=np.float64).tolist(), np.asarray(triangles).tolist())

    def cast(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        distances = np.full(len(origins), np.inf)
        for index, (origin, direction) in enumerate(zip(np.asarray(origins, float), np.asarray(directions, float))):
            hit = tree.ray_cast(Vector(origin), Vector(direction))
            if hit[0] is not None:
                distances[index] = hit[3]
        return distances

    return cast


def _file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def build_mesh_scene(config: MeshSceneConfig, *, scene: bpy.types.Scene | None = None,
                     progress: Callable[[ProgressEvent], None] | None = None) -> dict[str, Any]:
    """Import ``config.mesh``, make it render as observed, place the rig's cameras.

    Returns a dict with ``collection``, ``terrain`` (the one mesh object), ``rocks`` (empty),
    ``cameras`` (objects, in view order), ``poses`` (CameraPose list), ``world``, ``config``
    and ``scene_info`` (the scene.json entries that describe the mesh source). Raises
    :class:`DatasetError` naming the file for a missing, unreadable or empty mesh or a rig
    that cannot be placed; nothing created is left behind then.
    """
    from .cameras import camera_object_from_opencv
    from .render_dataset import world_mesh_arrays
    from .terrain_scene import apply_render_settings

    config.validate()
    path = check_mesh_file(config.mesh)
    scene = scene or bpy.context.scene
    report = progress or (lambda event: None)
    total = 4
    new_data = _NewData()
    previous_world = scene.world
    try:
        report(ProgressEvent(0, total, "scene", message=f"importing {path.name}"))
        imported = import_mesh_file(path)
        if not any(obj.type == "MESH" and len(obj.data.polygons) > 0 for obj in imported):
            raise DatasetError("the mesh file holds no faces", path=path, hint="export the surface as triangles")
        collection = bpy.data.collections.new(f"ESGS mesh {config.name} s{config.seed}")
        scene.collection.children.link(collection)
        report(ProgressEvent(1, total, "scene", message="joining and cleaning the mesh"))
        terrain = _bake_and_join(imported, collection)
        terrain[PROP_ROLE] = "terrain"
        vertices = np.empty(len(terrain.data.vertices) * 3, dtype=np.float32)
        terrain.data.vertices.foreach_get("co", vertices)
        vertices = vertices.reshape(-1, 3)
        extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0))) if len(vertices) else 0.0
        if extent <= 0:
            raise DatasetError("the mesh has no extent (all vertices coincide)", path=path)
        clean_mesh(terrain.data, merge_distance=0.0)  # bit-identical positions only
        if len(terrain.data.polygons) == 0:
            raise DatasetError("the mesh has no faces with an area", path=path)
        if not terrain.data.materials:
            terrain.data.materials.append(bpy.data.materials.new("ESGS mesh grey"))
        for material in {m.as_pointer(): m for m in terrain.data.materials if m is not None}.values():
            make_emission_material(material)

        if config.rig.kind == "mixed":
            # rover views see the sky: a Mars sky gradient (emission-only terrain is not lit by it)
            from .mars_material import make_sky_world

            world = make_sky_world("ESGS mesh sky", sky=True, sun_elevation_deg=90.0)
        else:
            world = bpy.data.worlds.new("ESGS black")
            if world.node_tree is None:
                world.use_nodes = True
            background = next(node for node in world.node_tree.nodes if node.type == "BACKGROUND")
            background.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
            background.inputs["Strength"].default_value = 0.0
        scene.world = world

        report(ProgressEvent(2, total, "scene", message=f"placing {config.rig.views} '{config.rig.kind}' cameras"))
        world_vertices, triangles, _ = world_mesh_arrays({"terrain": terrain})
        cast = bvh_ray_caster(world_vertices, triangles)
        poses = make_mesh_rig(config.rig, config.render, cast, world_vertices.min(axis=0), world_vertices.max(axis=0),
                              seed=config.seed, source=path)
        cameras = []
        for pose in poses:
            camera = camera_object_from_opencv(pose.name, pose.K, pose.world_to_camera, pose.width, pose.height,
                                               collection=collection)
            camera.data.clip_start = float(config.render.near_m)
            camera.data.clip_end = float(config.render.far_m)
            camera[PROP_ROLE] = "camera"
            cameras.append(camera)
        report(ProgressEvent(3, total, "scene", message="render settings"))
        apply_render_settings(scene, config.render)
        scene.camera = cameras[0]
    except BaseException:
        scene.world = previous_world
        new_data.remove_all()
        raise
    low, high = world_vertices.min(axis=0), world_vertices.max(axis=0)
    scene_info = {
        "source": "mesh",
        "generator": "esgs.esgs_addon.mesh_scene",
        "generator_version": GENERATOR_VERSION,
        "world_frame": ("the mesh file's frame as Blender imports it (glTF +Y up becomes +Z up: "
                        "(x, y, z)_gltf -> (x, -z, y)); units of the file"),
        "mesh_source": {"path": str(path), "sha256": _file_sha256(path), "vertices": int(len(world_vertices)),
                        "triangles": int(len(triangles)), "bounds_min": low.tolist(), "bounds_max": high.tolist()},
        "appearance": "unlit: the mesh's base colour / texture emitted at strength 1, black world, no lamps",
        "rig": config_to_dict(config.rig),
    }
    report(ProgressEvent(total, total, "scene", kind="done",
                         message=f"mesh scene '{collection.name}': {len(triangles)} triangles, {len(cameras)} cameras"))
    return {"collection": collection, "terrain": terrain, "rocks": [], "cameras": cameras, "poses": list(poses),
            "world": world, "config": config, "scene_info": scene_info}
