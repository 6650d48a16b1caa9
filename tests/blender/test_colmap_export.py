"""Blender cameras -> COLMAP model (export_cameras_to_colmap, esgs.export_colmap) and back."""
from __future__ import annotations

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from bpy_extras.object_utils import world_to_camera_view  # noqa: E402
from mathutils import Euler, Vector  # noqa: E402

from esgs.core.colmap.io import read_model  # noqa: E402
from esgs.core.errors import ConfigError, ESGSError  # noqa: E402
from esgs.esgs_addon import cameras  # noqa: E402
from esgs.esgs_addon.colmap_scene import ColmapImportOptions, export_cameras_to_colmap, import_colmap_scene  # noqa: E402
from tests.blender.colmap_helpers import maupertuis_scene, synthetic_model, tilt_rotation, write_scene  # noqa: E402


def hand_made_cameras() -> list[bpy.types.Object]:
    """Cameras set up the way a Blender user would: lens, AUTO/VERTICAL fit, shifts, rotations."""
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = 800, 600
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = 1.0, 1.1
    made = []
    settings = [
        ("wide", 24.0, "AUTO", 0.05, -0.02, (1.0, -7.0, 2.0), (80, 0, 5)),
        ("tele", 85.0, "VERTICAL", -0.1, 0.07, (-3.0, 4.0, 6.5), (60, 10, 200)),
        ("plain", 50.0, "HORIZONTAL", 0.0, 0.0, (0.5, 0.5, 12.0), (0, 0, 33)),
    ]
    for name, lens, fit, shift_x, shift_y, location, rotation_deg in settings:
        data = bpy.data.cameras.new(name)
        data.lens, data.sensor_fit, data.shift_x, data.shift_y = lens, fit, shift_x, shift_y
        data.sensor_height = 20.0
        obj = bpy.data.objects.new(name, data)
        obj.location = location
        obj.rotation_euler = Euler([np.radians(v) for v in rotation_deg])
        scene.collection.objects.link(obj)
        made.append(obj)
    bpy.context.view_layer.update()
    return made


def projections(scene, obj, points: np.ndarray) -> np.ndarray:
    width, height = cameras.render_size(scene)
    result = []
    for point in points:
        ndc = world_to_camera_view(scene, obj, Vector(point.tolist()))
        result.append((ndc.x * width, (1 - ndc.y) * height))
    return np.array(result)


def test_blender_to_colmap_to_blender_keeps_cameras(tmp_path):
    scene = bpy.context.scene
    originals = hand_made_cameras()
    expected = {obj.name: cameras.opencv_from_camera_object(obj, scene) for obj in originals}
    rng = np.random.default_rng(0)
    points = rng.uniform(-3, 3, size=(40, 3))
    expected_pixels = {obj.name: projections(scene, obj, points) for obj in originals}

    model = export_cameras_to_colmap(scene, tmp_path / "scene" / "sparse" / "0")
    written = read_model(tmp_path / "scene" / "sparse" / "0")
    assert sorted(image.name for image in written.images.values()) == ["plain.png", "tele.png", "wide.png"]
    assert len(written.points) == 0
    assert all(camera.model == "PINHOLE" for camera in written.cameras.values())
    for image in written.images.values():
        K, world_to_camera, width, height = expected[image.name[:-4]]
        camera = written.cameras[image.camera_id]
        assert (camera.width, camera.height) == (width, height) == (800, 600)
        np.testing.assert_allclose(camera.K(), K, atol=1e-6, rtol=0)
        np.testing.assert_allclose(image.world_to_camera(), world_to_camera, atol=1e-6, rtol=0)
        assert model.images[image.image_id].name == image.name
    # pixels 1.1 times taller than wide: fewer pixels per unit angle vertically, fx = 1.1 fy
    first = next(iter(written.cameras.values()))
    np.testing.assert_allclose(first.params[0] / first.params[1], 1.1, rtol=1e-6)

    for obj in originals:
        bpy.data.objects.remove(obj)
    result = import_colmap_scene(tmp_path / "scene")
    assert len(result["cameras"]) == 3
    for obj in result["cameras"]:
        name = obj.name[:-4]
        K, world_to_camera, width, height = cameras.opencv_from_camera_object(obj, scene)
        K0, pose0, width0, height0 = expected[name]
        assert (width, height) == (width0, height0)
        np.testing.assert_allclose(K, K0, atol=1e-6, rtol=0)
        np.testing.assert_allclose(world_to_camera, pose0, atol=1e-6, rtol=0)
        # and Blender itself projects as the original cameras did
        np.testing.assert_allclose(projections(scene, obj, points), expected_pixels[name], atol=1e-3)


def test_export_undoes_the_orientation_and_keeps_ids(tmp_path):
    source = synthetic_model(sizes=((640, 480),), ground_rotation=tilt_rotation())
    scene_dir = write_scene(tmp_path, source)
    result = import_colmap_scene(scene_dir, ColmapImportOptions(orient_up=True))
    assert not np.allclose(result["transform"], np.eye(4))
    export_cameras_to_colmap(result["cameras"], tmp_path / "out", binary=False)
    written = read_model(tmp_path / "out")
    assert (tmp_path / "out" / "cameras.txt").is_file()
    assert set(written.images) == set(source.images)
    for image_id, image in written.images.items():
        original = source.images[image_id]
        assert image.name == original.name
        np.testing.assert_allclose(image.world_to_camera(), original.world_to_camera(), atol=1e-6, rtol=0)
        np.testing.assert_allclose(written.cameras[image.camera_id].K(), source.cameras[1].K(), atol=1e-6)
    assert len(written.cameras) == 1


def test_export_real_model_round_trip(tmp_path):
    scene_dir = maupertuis_scene(tmp_path)
    import_colmap_scene(scene_dir, ColmapImportOptions(orient_up=True, import_points=False))
    assert bpy.ops.esgs.export_colmap(directory=str(tmp_path / "exported")) == {"FINISHED"}
    original = read_model(scene_dir)
    written = read_model(tmp_path / "exported")
    assert len(written.images) == 4 and len(written.cameras) == 1
    camera = written.cameras[next(iter(written.cameras))]
    np.testing.assert_allclose(camera.params, [1847.53, 1847.53, 959.5, 539.5], atol=1e-6)
    for image_id, image in written.images.items():
        np.testing.assert_allclose(image.world_to_camera(), original.images[image_id].world_to_camera(), atol=1e-6)


def test_export_refuses_bad_requests(tmp_path):
    with pytest.raises(ConfigError, match="no cameras"):
        export_cameras_to_colmap(bpy.context.scene, tmp_path / "none")
    mesh_object = bpy.data.objects.new("empty", None)
    with pytest.raises(ConfigError, match="not a camera"):
        export_cameras_to_colmap([mesh_object], tmp_path / "none")
    assert not (tmp_path / "none").exists()
    hand_made_cameras()
    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "notes.txt").write_text("keep me")
    with pytest.raises(ESGSError):
        export_cameras_to_colmap(bpy.context.scene, occupied)
    assert [p.name for p in occupied.iterdir()] == ["notes.txt"]
    with pytest.raises(RuntimeError):
        bpy.ops.esgs.export_colmap(directory=str(occupied))
    export_cameras_to_colmap(bpy.context.scene, occupied, overwrite=True)
    assert len(read_model(occupied).images) == 3
