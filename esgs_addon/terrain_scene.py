"""Build a synthetic Mars scene in Blender from a :class:`~esgs.core.terrain.SceneConfig`.

Public entry point: :func:`build_terrain_scene`. It generates the terrain with the core
engine (heightfield, sand mask, rocks, camera rig), then creates in one new collection:

* the terrain mesh (one vertex per heightfield sample, triangles, flat shaded, the sand
  mask as the ``esgs_sand`` point attribute) with the procedural Mars material;
* the rocks: a handful of irregular prototype meshes (deformed, facet-cut icospheres) and
  one linked duplicate per rock, scaled, turned and partly buried as the core placed it;
* a sun lamp from the solar elevation and azimuth, and a world (Mars sky or black);
* one camera per view of the rig, exactly matching the OpenCV cameras.

The terrain is smooth shaded (Blender's vertex normals, interpolated across each
triangle), the rocks flat shaded (their cut faces are meant to look like fractures).
Cycles' Normal pass is exactly that shading normal, and the exported ground-truth mesh
carries the same normals per vertex (rock vertices unshared), so the normal priors and the
mesh agree. The materials never bend the normal (no bump maps).
"""
from __future__ import annotations

import json
import math
from typing import Any, Callable

import bpy
import numpy as np
from mathutils import Matrix, Vector

from ..core.config import config_to_dict
from ..core.errors import ConfigError
from ..core.progress import ProgressEvent
from ..core.terrain.palette import scene_palette
from .mars_material import SAND_ATTRIBUTE, make_rock_material, make_sky_world, make_terrain_material

#: Version of the scene generator; bump when the same config would give different output.
GENERATOR_VERSION = "1.1"  # 1.1: dune lag patches, overlapping pans, bounded wander

#: Custom properties that let :func:`scene_objects_from_collection` find the parts again.
PROP_ROLE = "esgs_role"
PROP_CONFIG = "esgs_scene_config"
PROP_GENERATOR = "esgs_generator_version"

#: Number of distinct rock shapes; each rock picks one from its ``shape_seed``.
ROCK_PROTOTYPES = 12
#: Icosphere subdivisions of small rocks (162 vertices: cheap for thousands of rocks) and of
#: rocks at least LARGE_ROCK_DIAMETER_M across (642 vertices: close-ups stay rock-like).
_ROCK_SUBDIVISIONS = (2, 3)
LARGE_ROCK_DIAMETER_M = 0.8

# Mars receives ~43 % of Earth's sunlight; with the Standard view transform a sun of this
# strength exposes regolith albedos (~0.3) to mid-grey, as rover images are exposed.
SUN_STRENGTH_W_M2 = 3.0
SUN_ANGULAR_DIAMETER_DEG = 0.35  # the Sun seen from Mars


def heightfield_grid(heights: np.ndarray, extent_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a square heightfield centred on the origin.

    heights: [R, R] metres, row index along +y, column index along +x (``heights[iy, ix]``
    is the height at ``x = -extent/2 + ix * cell``, ``y = -extent/2 + iy * cell``).
    Returns (vertices [R*R, 3] float64, triangles [2*(R-1)^2, 3] int32), counter-clockwise
    seen from above so face normals point up.
    """
    heights = np.asarray(heights, dtype=np.float64)
    if heights.ndim != 2 or heights.shape[0] != heights.shape[1] or heights.shape[0] < 2:
        raise ConfigError(f"heightfield must be square [R, R] with R >= 2, got shape {heights.shape}")
    resolution = heights.shape[0]
    axis = np.linspace(-extent_m / 2.0, extent_m / 2.0, resolution)
    x, y = np.meshgrid(axis, axis)  # x varies along columns, y along rows
    vertices = np.stack([x.ravel(), y.ravel(), heights.ravel()], axis=1)
    row, col = np.meshgrid(np.arange(resolution - 1), np.arange(resolution - 1), indexing="ij")
    corner = (row * resolution + col).ravel()
    # corner (x, y), +x neighbour, +x+y, +y: counter-clockwise around +z
    a, b, c, d = corner, corner + 1, corner + 1 + resolution, corner + resolution
    triangles = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    return vertices, triangles


def mesh_from_arrays(name: str, vertices: np.ndarray, triangles: np.ndarray, *, smooth: bool = False) -> bpy.types.Mesh:
    """A Blender mesh from vertices [V, 3] and triangles [F, 3], without Python loops.

    ``smooth`` shades with interpolated vertex normals; otherwise every face is flat.
    """
    mesh = bpy.data.meshes.new(name)
    try:
        mesh.vertices.add(len(vertices))
        mesh.vertices.foreach_set("co", np.ascontiguousarray(vertices, dtype=np.float32).ravel())
        mesh.loops.add(triangles.size)
        mesh.loops.foreach_set("vertex_index", np.ascontiguousarray(triangles, dtype=np.int32).ravel())
        mesh.polygons.add(len(triangles))
        mesh.polygons.foreach_set("loop_start", np.arange(0, triangles.size, 3, dtype=np.int32))
        mesh.update()
        if smooth:
            mesh.shade_smooth()
        else:
            mesh.shade_flat()
    except Exception:
        bpy.data.meshes.remove(mesh)
        raise
    return mesh


def rock_shape_parameters(rng: np.random.Generator) -> dict[str, Any]:
    """Random parameters of one rock shape (lumps, fracture planes, stretch); see :func:`rock_prototype_geometry`."""
    waves = []
    for _ in range(4):
        frequency = rng.normal(size=3)
        frequency *= rng.uniform(1.5, 3.5) / np.linalg.norm(frequency)
        waves.append((frequency, rng.uniform(0.04, 0.12), rng.uniform(0, 2 * math.pi)))
    planes = []
    for _ in range(int(rng.integers(3, 7))):
        normal = rng.normal(size=3)
        planes.append((normal / np.linalg.norm(normal), rng.uniform(0.55, 0.85)))
    return {"waves": waves, "planes": planes, "stretch_y": rng.uniform(0.65, 1.0)}


def rock_prototype_geometry(shape: dict[str, Any], subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """One irregular rock: (vertices [V, 3], triangles [F, 3]) from :func:`rock_shape_parameters`.

    A unit icosphere (``subdivisions`` levels) is made lumpy with a few random
    low-frequency waves, cut by a few random planes (the flat fracture faces of real
    rocks), stretched a little, then fitted into the unit footprint: ``x, y`` within a 1 m
    diameter, ``z`` from 0 (base) to 1 (top). Scaling the object by (diameter, diameter,
    height) gives the rock the core asked for. The same parameters at another subdivision
    level give the same rock, finer or coarser.
    """
    import bmesh

    bm = bmesh.new()
    try:
        bmesh.ops.create_icosphere(bm, subdivisions=int(subdivisions), radius=1.0)
        bm.verts.ensure_lookup_table()
        vertices = np.array([v.co for v in bm.verts], dtype=np.float64)
        bmesh.ops.triangulate(bm, faces=bm.faces[:])
        triangles = np.array([[v.index for v in f.verts] for f in bm.faces], dtype=np.int32)
    finally:
        bm.free()
    directions = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    radius = np.ones(len(vertices))
    for frequency, amplitude, phase in shape["waves"]:
        radius += amplitude * np.cos(directions @ frequency + phase)
    points = directions * radius[:, None]
    for normal, offset in shape["planes"]:
        excess = np.maximum(points @ normal - offset, 0.0)
        points -= excess[:, None] * normal[None, :]
    points *= np.array([1.0, shape["stretch_y"], 1.0])
    low, high = points.min(axis=0), points.max(axis=0)
    centre_xy = (low[:2] + high[:2]) / 2.0
    footprint = max(high[0] - low[0], high[1] - low[1])
    points[:, :2] = (points[:, :2] - centre_xy) / footprint
    points[:, 2] = (points[:, 2] - low[2]) / (high[2] - low[2])
    return points, triangles


def add_sun(name: str, direction_to_sun: tuple[float, float, float], collection: bpy.types.Collection,
            strength: float = SUN_STRENGTH_W_M2) -> bpy.types.Object:
    """A sun lamp shining along ``-direction_to_sun`` (a world-frame unit vector toward the sun)."""
    light = bpy.data.lights.new(name, "SUN")
    light.energy = strength
    light.angle = math.radians(SUN_ANGULAR_DIAMETER_DEG)
    sun = bpy.data.objects.new(name, light)
    # a sun lamp emits along its local -Z: point local +Z at the sun
    rotation = Vector(direction_to_sun).to_track_quat("Z", "Y")
    # placement only matters for display; matrix_world (not location/rotation) is up to date at once
    sun.matrix_world = Matrix.LocRotScale(Vector(direction_to_sun) * 50.0, rotation, None)
    collection.objects.link(sun)
    return sun


def apply_render_settings(scene: bpy.types.Scene, render_config: Any) -> None:
    """Cycles on the CPU with the config's samples, denoised, at the config's resolution.

    The Standard view transform keeps pixel values proportional to reflected light (no
    filmic curve), which is what a reconstruction method expects from calibrated images.
    """
    from .cameras import set_scene_resolution_from_camera

    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(render_config.samples)
    scene.cycles.use_adaptive_sampling = True
    scene.cycles.use_denoising = True
    scene.cycles.denoising_prefilter = "FAST"  # ACCURATE costs ~40 % more CPU time per view for no visible gain here
    scene.cycles.denoiser = "OPENIMAGEDENOISE"
    # regolith scenes need little indirect light; fewer bounces keep renders fast
    scene.cycles.max_bounces = 4
    scene.cycles.diffuse_bounces = 2
    scene.cycles.glossy_bounces = 1
    scene.cycles.transmission_bounces = 0
    scene.cycles.volume_bounces = 0
    scene.cycles.transparent_max_bounces = 0
    scene.render.use_persistent_data = True  # keep the BVH between the views of one scene
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    focal = render_config.focal_px
    set_scene_resolution_from_camera(scene, int(render_config.width), int(render_config.height), focal, focal)
    scene.render.image_settings.media_type = "IMAGE"
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_depth = "8"
    scene.render.image_settings.color_mode = "BW" if render_config.grayscale else "RGB"
    scene.render.image_settings.compression = 15


class _Created:
    """Everything :func:`build_terrain_scene` made, so a failure can remove all of it."""

    def __init__(self) -> None:
        self.ids: list[tuple[Any, Any]] = []

    def add(self, collection: Any, datablock: Any) -> Any:
        self.ids.append((collection, datablock))
        return datablock

    def remove_all(self) -> None:
        for collection, datablock in reversed(self.ids):
            try:
                collection.remove(datablock)
            except (ReferenceError, RuntimeError):
                pass  # already gone with its owner
        self.ids.clear()


def build_terrain_scene(config: Any, *, scene: bpy.types.Scene | None = None,
                        progress: Callable[[ProgressEvent], None] | None = None) -> dict[str, Any]:
    """Create the whole synthetic scene for ``config`` (a SceneConfig) in ``scene``.

    Returns a dict with ``collection``, ``terrain`` (object), ``rocks`` (objects),
    ``rock_meshes``, ``sun``, ``cameras`` (objects, in view order), ``poses`` (the core's
    CameraPose list), ``world``, ``config`` and ``terrain_data`` (the core Terrain).
    Raises :class:`ConfigError` for an invalid config before anything is created; on any
    other failure everything created so far is removed again.
    """
    from ..core.terrain import generate_terrain, make_camera_rig
    from .cameras import camera_object_from_opencv

    config.validate()
    scene = scene or bpy.context.scene
    report = progress or (lambda event: None)
    total = 4
    report(ProgressEvent(0, total, "scene", message="generating terrain"))
    terrain = generate_terrain(config.terrain, seed=config.seed)
    poses = make_camera_rig(config.rig, config.render, terrain, seed=config.seed)

    created = _Created()
    previous_world = scene.world
    try:
        collection = created.add(bpy.data.collections, bpy.data.collections.new(f"ESGS {config.name} s{config.seed}"))
        scene.collection.children.link(collection)
        collection[PROP_CONFIG] = json.dumps(config_to_dict(config))
        collection[PROP_GENERATOR] = GENERATOR_VERSION

        report(ProgressEvent(1, total, "scene", message="building terrain mesh"))
        vertices, triangles = heightfield_grid(terrain.heights, terrain.extent_m)
        terrain_mesh = created.add(bpy.data.meshes, mesh_from_arrays("ESGS terrain", vertices, triangles, smooth=True))
        sand = terrain_mesh.attributes.new(SAND_ATTRIBUTE, "FLOAT", "POINT")
        sand.data.foreach_set("value", np.asarray(terrain.sand_mask, dtype=np.float32).ravel())
        palette = scene_palette(config.palette, config.seed)
        terrain_material = created.add(bpy.data.materials, make_terrain_material(saturation=palette.surface_saturation))
        terrain_mesh.materials.append(terrain_material)
        terrain_object = created.add(bpy.data.objects, bpy.data.objects.new("ESGS terrain", terrain_mesh))
        terrain_object[PROP_ROLE] = "terrain"
        collection.objects.link(terrain_object)

        report(ProgressEvent(2, total, "scene", message=f"placing {len(terrain.rocks)} rocks"))
        rock_objects, rock_meshes = _add_rocks(terrain.rocks, config.seed, collection, created,
                                               saturation=palette.surface_saturation)

        report(ProgressEvent(3, total, "scene", message="sun, sky and cameras"))
        sun = created.add(bpy.data.objects, add_sun("ESGS sun", config.sun_direction(), collection))
        created.add(bpy.data.lights, sun.data)
        sun[PROP_ROLE] = "sun"
        world = created.add(bpy.data.worlds, make_sky_world("ESGS Mars sky", sky=config.sky,
                                                              sun_elevation_deg=config.sun_elevation_deg,
                                                              palette=palette))
        cameras = []
        for pose in poses:
            camera = camera_object_from_opencv(pose.name, pose.K, pose.world_to_camera, pose.width, pose.height,
                                               collection=collection)
            created.add(bpy.data.objects, camera)
            created.add(bpy.data.cameras, camera.data)
            camera.data.clip_start = float(config.render.near_m)
            camera.data.clip_end = float(config.render.far_m)
            camera[PROP_ROLE] = "camera"
            cameras.append(camera)

        scene.world = world
        apply_render_settings(scene, config.render)
        if cameras:
            scene.camera = cameras[0]
    except BaseException:
        scene.world = previous_world
        created.remove_all()
        raise
    report(ProgressEvent(total, total, "scene", kind="done",
                         message=f"scene '{collection.name}': {len(rock_objects)} rocks, {len(cameras)} cameras"))
    return {
        "collection": collection,
        "terrain": terrain_object,
        "rocks": rock_objects,
        "rock_meshes": rock_meshes,
        "sun": sun,
        "world": world,
        "cameras": cameras,
        "poses": list(poses),
        "config": config,
        "terrain_data": terrain,
    }


def _add_rocks(rocks: np.ndarray, seed: int, collection: bpy.types.Collection,
               created: _Created, *, saturation: float = 1.0) -> tuple[list[bpy.types.Object], list[bpy.types.Mesh]]:
    """Linked duplicates of a few prototype meshes, one per row of ``rocks`` [M, 7].

    Columns: x, y, z_base (height of the rock's base, already below the ground for the
    buried part), diameter_m, height_m, yaw_rad, shape_seed.
    """
    rocks = np.asarray(rocks, dtype=np.float64).reshape(-1, 7)
    if len(rocks) == 0:
        return [], []
    # prototypes depend on the scene seed only, so the same seed gives the same rocks
    rng = np.random.default_rng([int(seed), 0x526F636B])
    material = created.add(bpy.data.materials, make_rock_material(saturation=saturation))
    shape_index = rocks[:, 6].astype(np.int64) % ROCK_PROTOTYPES
    level = (rocks[:, 3] >= LARGE_ROCK_DIAMETER_M).astype(np.int64)
    used = set(zip(shape_index.tolist(), level.tolist()))
    meshes: dict[tuple[int, int], bpy.types.Mesh] = {}
    for index in range(ROCK_PROTOTYPES):
        # always draw every shape so a shape's geometry does not depend on which are used
        shape = rock_shape_parameters(rng)
        for detail in (0, 1):
            if (index, detail) in used:
                vertices, triangles = rock_prototype_geometry(shape, _ROCK_SUBDIVISIONS[detail])
                mesh = created.add(bpy.data.meshes, mesh_from_arrays(
                    f"ESGS rock shape {index}{' fine' if detail else ''}", vertices, triangles))
                mesh.materials.append(material)
                meshes[index, detail] = mesh
    objects = []
    for row, (x, y, z_base, diameter, height, yaw, shape_seed) in enumerate(rocks):
        rock = created.add(bpy.data.objects, bpy.data.objects.new(f"ESGS rock {row}",
                                                                 meshes[int(shape_index[row]), int(level[row])]))
        rock.matrix_world = Matrix.LocRotScale(Vector((x, y, z_base)), Matrix.Rotation(yaw, 3, "Z").to_quaternion(),
                                               Vector((diameter, diameter, height)))
        rock[PROP_ROLE] = "rock"
        collection.objects.link(rock)
        objects.append(rock)
    return objects, list(meshes.values())


def remove_terrain_scene(objects: dict[str, Any]) -> None:
    """Delete a scene made by :func:`build_terrain_scene` (objects, meshes, materials, world)."""
    collection = objects["collection"]
    datablocks: list[tuple[Any, Any]] = []
    for obj in list(collection.objects):
        datablocks.append((bpy.data.objects, obj))
        data = obj.data
        if isinstance(data, bpy.types.Mesh):
            datablocks.append((bpy.data.meshes, data))
            datablocks.extend((bpy.data.materials, m) for m in data.materials if m is not None)
        elif isinstance(data, bpy.types.Camera):
            datablocks.append((bpy.data.cameras, data))
        elif isinstance(data, bpy.types.Light):
            datablocks.append((bpy.data.lights, data))
    if objects.get("world") is not None:
        datablocks.append((bpy.data.worlds, objects["world"]))
    datablocks.append((bpy.data.collections, collection))
    seen: set[int] = set()
    for owner, block in datablocks:
        try:
            key = block.as_pointer()
        except ReferenceError:
            continue
        if key in seen:
            continue
        seen.add(key)
        owner.remove(block)


def scene_objects_from_collection(collection: bpy.types.Collection) -> dict[str, Any]:
    """Recover the dict of :func:`build_terrain_scene` from its collection (for the operators).

    The config comes back from the collection's stored JSON; camera poses from the camera
    objects (exact values, as stored by the camera importer).
    """
    from ..core.config import config_from_dict
    from ..core.terrain import SceneConfig

    if PROP_CONFIG not in collection:
        raise ConfigError(f"collection '{collection.name}' is not an ESGS synthetic scene",
                          hint="generate one with ESGS > Synthetic Mars scene > Generate")
    config = config_from_dict(SceneConfig, json.loads(collection[PROP_CONFIG]))
    by_role: dict[str, list[bpy.types.Object]] = {}
    for obj in collection.objects:
        by_role.setdefault(obj.get(PROP_ROLE, ""), []).append(obj)
    terrains = by_role.get("terrain", [])
    if len(terrains) != 1:
        raise ConfigError(f"collection '{collection.name}' has {len(terrains)} terrain objects, expected 1")
    return {
        "collection": collection,
        "terrain": terrains[0],
        "rocks": by_role.get("rock", []),
        "sun": (by_role.get("sun") or [None])[0],
        "world": None,
        "cameras": by_role.get("camera", []),
        "config": config,
    }
