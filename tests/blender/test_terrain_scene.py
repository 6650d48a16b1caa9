"""Building a synthetic Mars scene in Blender: geometry, rocks, sun, cameras, clean failure."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from esgs.core.config import config_to_dict  # noqa: E402
from esgs.core.errors import ConfigError  # noqa: E402
from esgs.core.terrain import RenderConfig, RigConfig, SceneConfig, TerrainConfig, generate_terrain  # noqa: E402


def small_config(**changes) -> SceneConfig:
    config = SceneConfig(
        name="small", seed=11, sky=True,
        terrain=TerrainConfig(resolution=65, extent_m=30.0, relief_wavelength_m=15.0, rock_abundance=0.1,
                              rock_min_diameter_m=0.5, rock_max_diameter_m=2.0),
        rig=RigConfig(kind="orbit", views=3, radius_m=8.0, height_m=3.0),
        render=RenderConfig(width=96, height=54, samples=2, camera="custom"),
    )
    for key, value in changes.items():
        setattr(config, key, value)
    return config


def _datablock_counts() -> dict[str, int]:
    return {name: len(getattr(bpy.data, name)) for name in
            ("objects", "meshes", "materials", "cameras", "lights", "worlds", "collections")}


def _mesh_vertices(obj) -> np.ndarray:
    vertices = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
    obj.data.vertices.foreach_get("co", vertices)
    return vertices.reshape(-1, 3)


def test_terrain_mesh_follows_the_heightfield():
    from esgs.esgs_addon.mars_material import SAND_ATTRIBUTE
    from esgs.esgs_addon.terrain_scene import build_terrain_scene

    config = small_config()
    objects = build_terrain_scene(config)
    terrain = generate_terrain(config.terrain, seed=config.seed)
    vertices = _mesh_vertices(objects["terrain"])
    resolution = config.terrain.resolution
    assert len(vertices) == resolution ** 2
    assert len(objects["terrain"].data.polygons) == 2 * (resolution - 1) ** 2
    np.testing.assert_allclose(vertices[:, 2], terrain.heights.ravel(), atol=1e-5)
    # spot-check the grid convention against the core's own height lookup
    for index in (0, 7, resolution + 3, resolution ** 2 - 1):
        x, y, z = vertices[index]
        assert terrain.height_at(x, y) == pytest.approx(z, abs=1e-4)
    sand = np.empty(resolution ** 2, dtype=np.float32)
    objects["terrain"].data.attributes[SAND_ATTRIBUTE].data.foreach_get("value", sand)
    np.testing.assert_allclose(sand, terrain.sand_mask.ravel(), atol=1e-6)
    # every face points up: the heightfield's triangles are counter-clockwise from above
    normals = np.empty(len(objects["terrain"].data.polygons) * 3, dtype=np.float32)
    objects["terrain"].data.polygons.foreach_get("normal", normals)
    assert normals.reshape(-1, 3)[:, 2].min() > 0
    assert objects["terrain"].name in objects["collection"].objects
    assert json.loads(objects["collection"]["esgs_scene_config"]) == config_to_dict(config)


def test_rocks_have_the_requested_size_and_place():
    from esgs.esgs_addon.terrain_scene import ROCK_PROTOTYPES, build_terrain_scene

    config = small_config()
    objects = build_terrain_scene(config)
    table = objects["terrain_data"].rocks
    assert len(table) > 5 and len(objects["rocks"]) == len(table)
    shapes = {rock.data.name for rock in objects["rocks"]}
    assert 1 < len(shapes) <= 2 * ROCK_PROTOTYPES  # several shapes, shared as linked duplicates
    assert len(shapes) < len(objects["rocks"])
    for rock, (x, y, z_base, diameter, height, yaw, _) in zip(objects["rocks"], table):
        local = _mesh_vertices(rock).astype(np.float64)
        matrix = np.array(rock.matrix_world)
        world = local @ matrix[:3, :3].T + matrix[:3, 3]
        assert world[:, 2].min() == pytest.approx(z_base, abs=1e-4)
        assert world[:, 2].max() == pytest.approx(z_base + height, abs=1e-4)
        # the footprint fits in the diameter and fills it along its longest direction
        radial = np.hypot(world[:, 0] - x, world[:, 1] - y)
        assert radial.max() <= diameter * 0.75 and radial.max() >= diameter * 0.4
        # partly buried: the base is below the ground at the rock's centre
        assert z_base < objects["terrain_data"].height_at(x, y)


def test_rock_prototypes_differ_and_fill_the_unit_box():
    from esgs.esgs_addon.terrain_scene import rock_prototype_geometry, rock_shape_parameters

    rng = np.random.default_rng(0)
    shape = rock_shape_parameters(rng)
    first, triangles = rock_prototype_geometry(shape)
    second, _ = rock_prototype_geometry(rock_shape_parameters(rng))
    fine, fine_triangles = rock_prototype_geometry(shape, subdivisions=3)
    assert first.shape == second.shape and not np.allclose(first, second)
    assert len(fine) > 3 * len(first) and len(fine_triangles) == 4 * len(triangles)
    # every coarse vertex is also a vertex of the finer icosphere: the same rock, refined
    from scipy.spatial import cKDTree

    distances, _ = cKDTree(fine).query(first)
    assert distances.max() < 0.05
    for shape in (first, second, fine):
        np.testing.assert_allclose(shape[:, 2].min(), 0.0, atol=1e-12)
        np.testing.assert_allclose(shape[:, 2].max(), 1.0, atol=1e-12)
        extent = shape.max(axis=0) - shape.min(axis=0)
        assert max(extent[0], extent[1]) == pytest.approx(1.0)
    assert triangles.min() == 0 and triangles.max() == len(first) - 1


def test_sun_cameras_and_render_settings():
    from esgs.esgs_addon.cameras import opencv_from_camera_object
    from esgs.esgs_addon.terrain_scene import build_terrain_scene

    config = small_config(sun_elevation_deg=20.0, sun_azimuth_deg=60.0)
    objects = build_terrain_scene(config)
    scene = bpy.context.scene
    # the lamp shines along its local -Z: from the sun toward the ground
    light_direction = np.array(objects["sun"].matrix_world.to_3x3().col[2])  # local +Z, toward the sun
    np.testing.assert_allclose(light_direction, config.sun_direction(), atol=1e-6)
    assert math.degrees(math.asin(config.sun_direction()[2])) == pytest.approx(20.0)
    assert [camera.name for camera in objects["cameras"]] == [pose.name for pose in objects["poses"]]
    for camera, pose in zip(objects["cameras"], objects["poses"]):
        K, world_to_camera, width, height = opencv_from_camera_object(camera, scene)
        np.testing.assert_allclose(K, pose.K, rtol=1e-12)
        np.testing.assert_allclose(world_to_camera, pose.world_to_camera, atol=1e-12)
        assert (width, height) == (96, 54)
    assert scene.render.engine == "CYCLES" and scene.cycles.device == "CPU"
    assert scene.cycles.samples == 2
    assert scene.world == objects["world"] and scene.world.cycles_visibility.camera


def test_sky_off_hides_the_world_from_the_camera():
    from esgs.esgs_addon.terrain_scene import build_terrain_scene

    config = small_config(sky=False)
    config.rig.pitch_deg = -60.0
    config.rig.radius_m = 3.0
    objects = build_terrain_scene(config)
    assert not objects["world"].cycles_visibility.camera


def test_bad_config_fails_before_creating_anything():
    from esgs.esgs_addon.terrain_scene import build_terrain_scene

    before = _datablock_counts()
    config = small_config()
    config.render.samples = 0
    with pytest.raises(ConfigError, match="render.samples"):
        build_terrain_scene(config)
    assert _datablock_counts() == before


def test_failure_while_building_removes_everything(monkeypatch):
    import esgs.esgs_addon.cameras as cameras
    from esgs.esgs_addon.terrain_scene import build_terrain_scene

    before = _datablock_counts()
    world_before = bpy.context.scene.world
    real = cameras.camera_object_from_opencv
    made = []

    def fail_on_third(*args, **kwargs):
        if len(made) == 2:
            raise RuntimeError("camera failed (simulated)")
        made.append(real(*args, **kwargs))
        return made[-1]

    monkeypatch.setattr(cameras, "camera_object_from_opencv", fail_on_third)
    with pytest.raises(RuntimeError, match="simulated"):
        build_terrain_scene(small_config())
    assert _datablock_counts() == before
    assert bpy.context.scene.world == world_before


def test_scene_objects_round_trip_through_the_collection():
    from esgs.esgs_addon.terrain_scene import build_terrain_scene, remove_terrain_scene, scene_objects_from_collection

    before = _datablock_counts()
    config = small_config()
    objects = build_terrain_scene(config)
    recovered = scene_objects_from_collection(objects["collection"])
    assert recovered["config"] == config
    assert recovered["terrain"] == objects["terrain"]
    assert sorted(r.name for r in recovered["rocks"]) == sorted(r.name for r in objects["rocks"])
    assert [c.name for c in recovered["cameras"]] == [c.name for c in objects["cameras"]]
    bpy.context.scene.world = None
    remove_terrain_scene(objects)
    assert _datablock_counts() == before


def test_generate_operator_builds_the_scene_from_the_panel_settings():
    settings = bpy.context.scene.esgs.terrain
    settings.preset = "cratered_plain"
    settings.seed = 3
    settings.views = 2
    settings.width, settings.height = 64, 36
    result = bpy.ops.esgs.generate_terrain()
    assert result == {"FINISHED"}
    collections = [c for c in bpy.data.collections if "esgs_scene_config" in c]
    assert len(collections) == 1
    config = json.loads(collections[0]["esgs_scene_config"])
    assert config["seed"] == 3 and config["rig"]["views"] == 2
    assert (config["render"]["width"], config["render"]["height"]) == (64, 36)
    assert len([o for o in collections[0].objects if o.type == "CAMERA"]) == 2
