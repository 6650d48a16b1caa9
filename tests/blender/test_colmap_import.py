"""COLMAP import into Blender (esgs_addon/colmap_scene.py, the operator, the panel)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
pycolmap = pytest.importorskip("pycolmap")

from bpy_extras.object_utils import world_to_camera_view  # noqa: E402
from mathutils import Vector  # noqa: E402

from esgs.core.colmap.io import read_model  # noqa: E402
from esgs.core.colmap.model import ColmapModel  # noqa: E402
from esgs.core.errors import DatasetError, ESGSError  # noqa: E402
from esgs.esgs_addon import cameras, colmap_scene, pointcloud  # noqa: E402
from esgs.esgs_addon.colmap_scene import ColmapImportOptions, import_colmap_scene  # noqa: E402
from tests.blender.colmap_helpers import maupertuis_scene, synthetic_model, tilt_rotation, write_scene  # noqa: E402

ID_COLLECTIONS = ("objects", "cameras", "meshes", "materials", "images", "pointclouds", "collections")


def datablock_counts() -> dict[str, int]:
    return {name: len(getattr(bpy.data, name)) for name in ID_COLLECTIONS}


def projection_disagreement(model: ColmapModel, result: dict) -> np.ndarray:
    """For every observation of every 3D point: |Blender projection - pycolmap projection| in px."""
    scene = bpy.context.scene
    by_image_id = {obj[colmap_scene.PROP_IMAGE_ID]: obj for obj in result["cameras"]}
    transform = result["transform"]
    errors = []
    for image in model.images.values():
        obj = by_image_id[image.image_id]
        camera = model.cameras[image.camera_id]
        cameras.use_camera(scene, obj)
        width, height = cameras.render_size(scene)
        assert (width, height) == (camera.width, camera.height)
        colmap_camera = pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height,
                                        params=np.asarray(camera.params, float))
        ids = [int(i) for i in image.point3d_ids if i >= 0 and int(i) in model.points]
        assert ids, "every image observes some points"
        xyz = np.stack([model.points[i].xyz for i in ids])
        camera_points = xyz @ image.rotation_matrix().T + image.translation
        expected = colmap_camera.img_from_cam(camera_points)
        blender_points = xyz @ transform[:3, :3].T + transform[:3, 3]
        for point, reference in zip(blender_points, expected):
            ndc = world_to_camera_view(scene, obj, Vector(point.tolist()))
            pixel = np.array([ndc.x * width, (1.0 - ndc.y) * height])
            errors.append(np.linalg.norm(pixel - reference))
    return np.array(errors)


# ----------------------------------------------------------------------------- real model


@pytest.mark.parametrize("orient_up", [False, True])
def test_maupertuis_projects_like_pycolmap(tmp_path, orient_up):
    scene_dir = maupertuis_scene(tmp_path)
    result = import_colmap_scene(scene_dir, ColmapImportOptions(orient_up=orient_up))
    model = read_model(scene_dir)
    errors = projection_disagreement(model, result)
    observations = sum(point.track_length for point in model.points.values())
    assert len(errors) == observations == 3355
    assert errors.mean() < 0.05
    assert errors.max() < 0.5


def test_maupertuis_collection_cameras_and_points(tmp_path):
    scene_dir = maupertuis_scene(tmp_path)
    before = {c.name for c in bpy.data.collections}
    result = import_colmap_scene(scene_dir)
    assert result["warnings"] == []
    new = [c for c in bpy.data.collections if c.name not in before]
    assert [c.name for c in new] == ["maupertuis"] and result["collection"] == new[0]
    collection = new[0]
    assert {obj.name for obj in collection.objects} == {"00.jpg", "01.jpg", "02.jpg", "03.jpg", "maupertuis points"}
    assert all(obj.users_collection == (collection,) for obj in collection.objects)
    scene = bpy.context.scene
    assert (scene.render.resolution_x, scene.render.resolution_y) == (1919, 1079)
    assert scene.camera == result["cameras"][0]
    # the stored transform is the identity without orient_up
    np.testing.assert_array_equal(np.array(collection[colmap_scene.PROP_TRANSFORM]).reshape(4, 4), np.eye(4))

    points = result["points"]
    assert points.type == "POINTCLOUD" and len(points.data.points) == 1039
    model = read_model(scene_dir)
    xyz, rgb, error, track_length = model.points_arrays()
    positions = pointcloud.read_point_attribute(points, "position")
    np.testing.assert_allclose(positions, xyz, atol=1e-5 * np.abs(xyz).max())
    np.testing.assert_allclose(pointcloud.read_point_attribute(points, "error"), error, rtol=1e-6)
    np.testing.assert_array_equal(pointcloud.read_point_attribute(points, "track_length"), track_length)
    assert track_length.sum() == 3355
    colour = pointcloud.read_point_attribute(points, "color")
    np.testing.assert_allclose(colour[:, :3], colmap_scene.srgb_to_linear(rgb / 255.0), atol=1e-6)
    assert points.data.attributes["color"].data_type == "FLOAT_COLOR"
    np.testing.assert_array_equal(np.round(pointcloud.read_point_attribute(points, "rgb")[:, :3] * 255), rgb)
    # the material shows the colour attribute
    material = points.data.materials[0]
    attribute_nodes = [n for n in material.node_tree.nodes if n.type == "ATTRIBUTE"]
    assert attribute_nodes and attribute_nodes[0].attribute_name == pointcloud.RENDER_COLOR_ATTRIBUTE
    assert attribute_nodes[0].outputs["Color"].is_linked


def test_image_planes_fill_the_camera_view(tmp_path):
    scene_dir = maupertuis_scene(tmp_path)
    result = import_colmap_scene(scene_dir, ColmapImportOptions(image_planes=True, image_plane_distance=2.5))
    planes = result["image_planes"]
    assert len(planes) == 4
    scene = bpy.context.scene
    bpy.context.view_layer.update()
    for plane, camera_object in zip(planes, result["cameras"]):
        assert plane.parent == camera_object and plane.hide_render
        image_node = [n for n in plane.data.materials[0].node_tree.nodes if n.type == "TEX_IMAGE"][0]
        assert Path(image_node.image.filepath).name == camera_object.name
        assert tuple(image_node.image.size) == (1919, 1079)
        corners = []
        for vertex in plane.data.vertices:
            world = plane.matrix_world @ vertex.co
            ndc = world_to_camera_view(scene, camera_object, world)
            corners.append((ndc.x, ndc.y, ndc.z))
        corners = np.array(corners)
        # the four image corners, at the requested depth
        np.testing.assert_allclose(sorted(map(tuple, np.round(corners[:, :2], 5))), [(0, 0), (0, 1), (1, 0), (1, 1)], atol=1e-4)
        np.testing.assert_allclose(corners[:, 2], 2.5, rtol=1e-5)
        # UV (0, 1) sits on the image's top-left corner
        uv = np.zeros(8, np.float32)
        plane.data.uv_layers[0].data.foreach_get("uv", uv)
        loops = np.zeros(4, np.int32)
        plane.data.loops.foreach_get("vertex_index", loops)
        for corner_uv, vertex_index in zip(uv.reshape(4, 2), loops):
            u, v = corners[vertex_index, :2]
            np.testing.assert_allclose(corner_uv, [u, v], atol=1e-4)


# ----------------------------------------------------------------------------- synthetic models


def test_synthetic_pinhole_portrait_and_landscape_project_like_pycolmap(tmp_path):
    model = synthetic_model()
    scene_dir = write_scene(tmp_path, model)
    result = import_colmap_scene(scene_dir)
    assert any("different image sizes" in warning for warning in result["warnings"])
    errors = projection_disagreement(read_model(scene_dir), result)
    assert len(errors) > 500
    assert errors.mean() < 0.05 and errors.max() < 0.2


def test_distorted_model_warns_and_keeps_parameters(tmp_path, capfd):
    model = synthetic_model(sizes=((640, 480),), model_name="OPENCV", extra_params=(0.01, -0.002, 0.001, 0.0005))
    scene_dir = write_scene(tmp_path, model)
    result = import_colmap_scene(scene_dir)
    assert len(result["warnings"]) == 1 and "OPENCV" in result["warnings"][0]
    for obj in result["cameras"]:
        assert obj[colmap_scene.PROP_DISTORTION_IGNORED] is True or obj[colmap_scene.PROP_DISTORTION_IGNORED] == 1
        assert obj[colmap_scene.PROP_CAMERA_MODEL] == "OPENCV"
        np.testing.assert_allclose(list(obj[colmap_scene.PROP_CAMERA_PARAMS]), model.cameras[1].params)
        K, _, _, _ = cameras.opencv_from_camera_object(obj, bpy.context.scene)
        np.testing.assert_allclose(K, model.cameras[1].K(), atol=1e-9)
    # the operator passes the warning on to the user
    capfd.readouterr()
    assert bpy.ops.esgs.import_colmap(directory=str(scene_dir)) == {"FINISHED"}
    printed = capfd.readouterr()
    assert "Warning" in printed.out + printed.err and "OPENCV" in printed.out + printed.err


def test_undistorted_folder_is_used_instead(tmp_path):
    distorted = synthetic_model(sizes=((640, 480),), model_name="OPENCV", extra_params=(0.01, 0.0, 0.0, 0.0))
    scene_dir = write_scene(tmp_path, distorted, name="rover")
    pinhole = synthetic_model(sizes=((600, 450),), seed=1)
    undistorted_dir = write_scene(tmp_path, pinhole, name="dense")
    result = import_colmap_scene(scene_dir, ColmapImportOptions(undistorted_path=str(undistorted_dir)))
    assert result["warnings"] == []
    assert result["collection"].name == "rover"
    K, _, width, height = cameras.opencv_from_camera_object(result["cameras"][0], bpy.context.scene)
    assert (width, height) == (600, 450)
    np.testing.assert_allclose(K, pinhole.cameras[1].K(), atol=1e-9)
    with pytest.raises(DatasetError):
        import_colmap_scene(undistorted_dir, ColmapImportOptions(undistorted_path=str(scene_dir)))


def test_orient_up_levels_a_tilted_ground(tmp_path):
    model = synthetic_model(sizes=((640, 480),), ground_rotation=tilt_rotation())
    scene_dir = write_scene(tmp_path, model)
    result = import_colmap_scene(scene_dir, ColmapImportOptions(orient_up=True))
    transform = np.array(result["collection"][colmap_scene.PROP_TRANSFORM]).reshape(4, 4)
    np.testing.assert_allclose(transform, result["transform"], atol=0)
    np.testing.assert_allclose(transform[:3, :3] @ transform[:3, :3].T, np.eye(3), atol=1e-12)
    positions = pointcloud.read_point_attribute(result["points"], "position").astype(np.float64)
    # ground flat (bumps of 5 cm) around z = 0, cameras above it
    assert np.abs(positions[:, 2]).max() < 0.3
    assert abs(np.median(positions[:, 2])) < 0.05
    for obj in result["cameras"]:
        assert obj.matrix_world.translation.z > 4.0
    # the projections are unchanged by the re-orientation
    errors = projection_disagreement(read_model(scene_dir), result)
    assert errors.mean() < 0.05


# ----------------------------------------------------------------------------- errors


def test_folder_without_model_creates_nothing(tmp_path):
    (tmp_path / "empty" / "images").mkdir(parents=True)
    before = datablock_counts()
    with pytest.raises(DatasetError, match="no COLMAP model"):
        import_colmap_scene(tmp_path / "empty")
    assert datablock_counts() == before
    with pytest.raises(RuntimeError, match="no COLMAP model"):
        bpy.ops.esgs.import_colmap(directory=str(tmp_path / "empty"))
    assert datablock_counts() == before


def test_truncated_model_creates_nothing(tmp_path):
    scene_dir = write_scene(tmp_path, synthetic_model())
    points_file = scene_dir / "sparse" / "0" / "points3D.bin"
    points_file.write_bytes(points_file.read_bytes()[:-7])
    before = datablock_counts()
    with pytest.raises(DatasetError):
        import_colmap_scene(scene_dir)
    assert datablock_counts() == before


def test_failure_while_building_removes_everything_created(tmp_path, monkeypatch):
    scene_dir = maupertuis_scene(tmp_path)
    before = datablock_counts()
    resolution = (bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y)

    def broken(*args, **kwargs):
        raise ESGSError("simulated failure after the cameras and image planes were built")

    monkeypatch.setattr(pointcloud, "point_cloud_object", broken)
    with pytest.raises(ESGSError, match="simulated"):
        import_colmap_scene(scene_dir, ColmapImportOptions(image_planes=True))
    assert datablock_counts() == before
    assert len(bpy.context.scene.collection.children) == 0
    assert (bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y) == resolution
    with pytest.raises(RuntimeError, match="simulated"):
        bpy.ops.esgs.import_colmap(directory=str(scene_dir))
    assert datablock_counts() == before


# ----------------------------------------------------------------------------- operator, panel, registration


def test_operator_imports_with_the_scene_settings(tmp_path):
    scene_dir = maupertuis_scene(tmp_path)
    settings = bpy.context.scene.esgs.colmap_import
    settings.image_planes = True
    settings.image_plane_distance = 3.0
    settings.collection_name = "roof"
    assert bpy.ops.esgs.import_colmap(directory=str(scene_dir)) == {"FINISHED"}
    assert bpy.context.scene.esgs.training.scene_dir == str(scene_dir)  # Training trains what was imported
    collection = bpy.data.collections["roof"]
    planes = [obj for obj in collection.objects if obj.type == "MESH"]
    assert len(planes) == 4
    assert all(plane["esgs_image_plane_distance"] == 3.0 for plane in planes)


def test_register_and_unregister(fresh_blender):
    import esgs

    assert hasattr(bpy.types, "ESGS_OT_import_colmap") and hasattr(bpy.types, "ESGS_OT_export_colmap")
    assert hasattr(bpy.types, "ESGS_PT_import")
    assert bpy.types.ESGS_PT_import.bl_parent_id == "ESGS_PT_main"
    settings = bpy.context.scene.esgs.colmap_import
    defaults = ColmapImportOptions()
    for name in ("import_points", "image_planes", "orient_up", "point_radius", "image_plane_distance"):
        assert getattr(settings, name) == pytest.approx(getattr(defaults, name))
    assert settings.orient_up is False
    import_entries = [f for f in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize() if "import_colmap" in f.__module__]
    assert len(import_entries) == 1
    esgs.unregister()
    try:
        assert not hasattr(bpy.types, "ESGS_OT_import_colmap")
        assert not hasattr(bpy.types, "ESGS_PT_import")
        assert not hasattr(bpy.types.Scene, "esgs")
        assert not [f for f in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize() if "import_colmap" in f.__module__]
    finally:
        esgs.register()
    assert hasattr(bpy.types, "ESGS_OT_import_colmap")


def test_point_colours_render_in_cycles():
    """The point material shows the colour attribute: a red and a blue cloud render as such."""
    scene = bpy.context.scene
    K = np.array([[40.0, 0, 32], [0, 40.0, 16], [0, 0, 1]])
    camera_object = cameras.camera_object_from_opencv("cam", K, np.eye(4), 64, 32)
    cameras.use_camera(scene, camera_object)
    rng = np.random.default_rng(0)
    # two dense clouds at depth 5, left half red and right half blue (OpenCV: z forward)
    left = np.column_stack([rng.uniform(-3.5, -0.5, 4000), rng.uniform(-1.8, 1.8, 4000), np.full(4000, 5.0)])
    right = left * np.array([-1, 1, 1])
    positions = np.vstack([left, right])  # world == OpenCV camera frame (identity pose)
    colours = np.vstack([np.tile([255, 0, 0], (4000, 1)), np.tile([0, 0, 255], (4000, 1))]).astype(np.uint8)
    pointcloud.point_cloud_object("dots", positions, {pointcloud.RENDER_COLOR_ATTRIBUTE: colours}, radius=0.08,
                                  material=pointcloud.point_color_material())
    scene.view_settings.view_transform = "Standard"
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 4
    scene.render.image_settings.file_format = "PNG"
    bpy.ops.render.render(write_still=False)
    result = bpy.data.images["Render Result"]
    # Render Result pixels are not readable directly; save and reload
    path = Path(bpy.app.tempdir or "/tmp") / f"esgs_points_{os.getpid()}.png"
    result.save_render(str(path))
    try:
        image = bpy.data.images.load(str(path))
        pixels = np.array(image.pixels[:]).reshape(32, 64, 4)  # bottom row first
        left_mean = pixels[8:24, 6:26, :3].mean(axis=(0, 1))
        right_mean = pixels[8:24, 38:58, :3].mean(axis=(0, 1))
    finally:
        path.unlink(missing_ok=True)
    assert left_mean[0] > 0.5 and left_mean[2] < 0.1
    assert right_mean[2] > 0.5 and right_mean[0] < 0.1


def test_example_script_saves_a_blend(tmp_path):
    import subprocess
    import sys

    from tests.conftest import REPO_ROOT

    scene_dir = maupertuis_scene(tmp_path)
    output = tmp_path / "out" / "roof.blend"
    completed = subprocess.run(
        [sys.executable, str(REPO_ROOT / "examples" / "import_colmap.py"), str(scene_dir), "--output", str(output),
         "--orient-up", "--image-planes", "--collection-name", "roof"],
        capture_output=True, text=True, timeout=120,
    )
    assert completed.returncode == 0, completed.stderr
    bpy.ops.wm.open_mainfile(filepath=str(output))
    collection = bpy.data.collections["roof"]
    assert sum(obj.type == "CAMERA" for obj in collection.objects) == 4
    assert sum(obj.type == "MESH" for obj in collection.objects) == 4
    assert len(bpy.data.objects["roof points"].data.points) == 1039
    assert not np.allclose(np.array(collection[colmap_scene.PROP_TRANSFORM]).reshape(4, 4), np.eye(4))

    failed = subprocess.run([sys.executable, str(REPO_ROOT / "examples" / "import_colmap.py"), str(tmp_path / "nothing")],
                            capture_output=True, text=True, timeout=120)
    assert failed.returncode == 1 and "folder not found" in failed.stderr


def test_importing_a_model_folder_chooses_its_scene_for_training(tmp_path):
    scene_dir = write_scene(tmp_path, synthetic_model())
    assert bpy.ops.esgs.import_colmap(directory=str(scene_dir / "sparse" / "0")) == {"FINISHED"}
    assert bpy.context.scene.esgs.training.scene_dir == str(scene_dir)  # the scene folder, not sparse/0
