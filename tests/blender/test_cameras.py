"""Blender camera <-> OpenCV camera conversion (esgs_addon/cameras.py)."""
from __future__ import annotations

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from bpy_extras.object_utils import world_to_camera_view  # noqa: E402
from mathutils import Vector  # noqa: E402

from esgs.core.colmap.geometry import quat_wxyz_to_matrix  # noqa: E402
from esgs.core.errors import ConfigError  # noqa: E402
from esgs.esgs_addon import cameras  # noqa: E402

# (width, height, fx, fy, cx, cy): landscape and portrait, fx > fy and fx < fy, off-centre
CASES = [
    (640, 480, 520.25, 498.5, 301.75, 255.125),
    (480, 720, 610.0, 655.5, 250.5, 340.25),
    (1919, 1079, 1847.53, 1847.53, 959.5, 539.5),
    (300, 900, 800.0, 700.0, 120.0, 500.0),
]


def random_pose(rng: np.random.Generator) -> np.ndarray:
    quat = rng.normal(size=4)
    matrix = np.eye(4)
    matrix[:3, :3] = quat_wxyz_to_matrix(quat)
    matrix[:3, 3] = rng.uniform(-30, 30, size=3)
    return matrix


def intrinsic_matrix(fx, fy, cx, cy) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def make_camera(case, pose):
    width, height, fx, fy, cx, cy = case
    K = intrinsic_matrix(fx, fy, cx, cy)
    scene = bpy.context.scene
    obj = cameras.camera_object_from_opencv("cam", K, pose, width, height)
    cameras.set_scene_resolution_from_camera(scene, width, height, fx, fy)
    scene.camera = obj
    bpy.context.view_layer.update()
    return obj, K


def project_blender(scene, obj, points: np.ndarray) -> np.ndarray:
    """[N, 3] world points -> [N, 2] COLMAP pixel coordinates through Blender's own projection."""
    width, height = cameras.render_size(scene)
    out = []
    for point in points:
        ndc = world_to_camera_view(scene, obj, Vector(point.tolist()))
        out.append((ndc.x * width, (1.0 - ndc.y) * height))
    return np.array(out)


def project_opencv(K, world_to_camera, points):
    camera_points = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    pixels = camera_points @ K.T
    return pixels[:, :2] / pixels[:, 2:3]


@pytest.mark.parametrize("case", CASES)
def test_round_trip_is_exact(case):
    rng = np.random.default_rng(1)
    pose = random_pose(rng)
    obj, K = make_camera(case, pose)
    K_back, pose_back, width, height = cameras.opencv_from_camera_object(obj, bpy.context.scene)
    assert (width, height) == case[:2]
    np.testing.assert_allclose(K_back, K, atol=1e-6, rtol=0)
    np.testing.assert_allclose(pose_back, pose, atol=1e-6, rtol=0)


@pytest.mark.parametrize("case", CASES)
def test_blender_state_alone_gives_the_camera_to_float32_precision(case):
    """Without the stored exact values the Blender settings themselves carry the camera."""
    rng = np.random.default_rng(2)
    pose = random_pose(rng)
    obj, K = make_camera(case, pose)
    for key in (cameras.PROP_K, cameras.PROP_WORLD_TO_CAMERA, cameras.PROP_SIZE):
        del obj[key]
    K_back, pose_back, _, _ = cameras.opencv_from_camera_object(obj, bpy.context.scene)
    np.testing.assert_allclose(K_back, K, rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(pose_back[:3, :3], pose[:3, :3], atol=1e-6)
    np.testing.assert_allclose(pose_back[:3, 3], pose[:3, 3], atol=1e-5)


@pytest.mark.parametrize("case", CASES)
def test_blender_projection_matches_opencv(case):
    rng = np.random.default_rng(3)
    pose = random_pose(rng)
    obj, K = make_camera(case, pose)
    width, height = case[:2]
    # points spread over (and a bit beyond) the image, at various depths
    pixels = rng.uniform([-0.1 * width, -0.1 * height], [1.1 * width, 1.1 * height], size=(50, 2))
    depth = rng.uniform(0.5, 40.0, size=50)
    rays = np.linalg.inv(K) @ np.vstack([pixels.T, np.ones(50)])
    camera_points = (rays * depth).T
    world_points = (camera_points - pose[:3, 3]) @ pose[:3, :3]
    projected = project_blender(bpy.context.scene, obj, world_points)
    assert np.abs(projected - pixels).max() < 1e-3
    np.testing.assert_allclose(project_opencv(K, pose, world_points), pixels, atol=1e-6)


def test_resolution_percentage_scales_intrinsics():
    case = CASES[0]
    obj, K = make_camera(case, np.eye(4))
    bpy.context.scene.render.resolution_percentage = 50
    K_half, _, width, height = cameras.opencv_from_camera_object(obj, bpy.context.scene)
    assert (width, height) == (320, 240)
    np.testing.assert_allclose(K_half[:2], K[:2] * 0.5, rtol=1e-6)


def test_edited_camera_is_read_from_blender_not_from_stored_values():
    obj, K = make_camera(CASES[1], np.eye(4))
    obj.data.lens *= 2.0
    obj.location.x += 1.0
    bpy.context.view_layer.update()
    K_back, pose_back, _, _ = cameras.opencv_from_camera_object(obj, bpy.context.scene)
    np.testing.assert_allclose(K_back[0, 0], 2 * K[0, 0], rtol=1e-6)
    # moving the camera +1 along world x moves the world -1 along camera x (identity rotation)
    np.testing.assert_allclose(pose_back[:3, 3], [-1.0, 0.0, 0.0], atol=1e-6)


def test_bad_input_raises_config_error():
    with pytest.raises(ConfigError):
        cameras.camera_object_from_opencv("bad", np.eye(2), np.eye(4), 10, 10)
    skewed = intrinsic_matrix(100, 100, 5, 5)
    skewed[0, 1] = 3.0
    with pytest.raises(ConfigError):
        cameras.camera_object_from_opencv("bad", skewed, np.eye(4), 10, 10)
    not_rotation = np.eye(4)
    not_rotation[0, 0] = 2.0
    with pytest.raises(ConfigError):
        cameras.camera_object_from_opencv("bad", intrinsic_matrix(100, 100, 5, 5), not_rotation, 10, 10)
    assert len(bpy.data.cameras) == 0 and len(bpy.data.objects) == 0


@pytest.mark.parametrize("case", [(160, 120, 150.0, 170.0, 70.3, 64.7), (90, 150, 160.0, 140.0, 52.2, 70.9)])
def test_cycles_renders_points_where_opencv_projects_them(case, tmp_path):
    """End to end through the renderer: pixel aspect, shifts and pose as Cycles sees them."""
    from esgs.esgs_addon import pointcloud

    width, height, fx, fy, cx, cy = case
    scene = bpy.context.scene
    rng = np.random.default_rng(4)
    pose = random_pose(rng)
    pose[:3, 3] /= 10
    K = intrinsic_matrix(fx, fy, cx, cy)
    obj = cameras.camera_object_from_opencv("cam", K, pose, width, height)
    cameras.use_camera(scene, obj)
    pixels = np.array([[u, v] for u in np.linspace(0.15, 0.85, 4) * width for v in np.linspace(0.15, 0.85, 3) * height])
    camera_points = np.column_stack([(pixels[:, 0] - cx) / fx, (pixels[:, 1] - cy) / fy, np.ones(len(pixels))]) * 10.0
    world_points = (camera_points - pose[:3, 3]) @ pose[:3, :3]
    pointcloud.point_cloud_object(
        "dots", world_points, {pointcloud.RENDER_COLOR_ATTRIBUTE: np.full((len(pixels), 3), 255, np.uint8)},
        radius=0.12, material=pointcloud.point_color_material(),
    )
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 64
    scene.cycles.pixel_filter_type = "BOX"
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.filepath = str(tmp_path / "render.exr")
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(str(tmp_path / "render.exr"))
    intensity = np.array(image.pixels[:]).reshape(height, width, 4)[::-1, :, 0]  # top row first
    errors = []
    for u, v in pixels:
        u0, v0, r = int(u), int(v), 6
        rows, columns = np.mgrid[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1]
        window = intensity[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1]
        centroid = np.array([(window * (columns + 0.5)).sum(), (window * (rows + 0.5)).sum()]) / window.sum()
        errors.append(np.linalg.norm(centroid - [u, v]))
    # a sphere's image centroid sits a little off its centre's projection; sampling noise on top
    assert np.mean(errors) < 0.12 and np.max(errors) < 0.3


@pytest.mark.parametrize("fit", ["AUTO", "HORIZONTAL", "VERTICAL"])
@pytest.mark.parametrize("aspect", [(1.0, 1.1), (1.1, 1.0), (1.0, 1.0)])
def test_intrinsics_of_any_blender_camera_match_blender_projection(fit, aspect):
    """Cameras not made by us: every sensor fit, with a pixel aspect that flips AUTO's choice."""
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = 640, 600
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = aspect
    data = bpy.data.cameras.new("user")
    data.lens, data.sensor_width, data.sensor_height = 42.0, 30.0, 22.0
    data.sensor_fit, data.shift_x, data.shift_y = fit, 0.07, -0.11
    obj = bpy.data.objects.new("user", data)
    obj.location = (1.0, -2.0, 3.0)
    obj.rotation_euler = (0.9, 0.1, -0.4)
    scene.collection.objects.link(obj)
    bpy.context.view_layer.update()
    K, pose, width, height = cameras.opencv_from_camera_object(obj, scene)
    rng = np.random.default_rng(5)
    pixels = rng.uniform([0, 0], [width, height], size=(20, 2))
    camera_points = np.column_stack([np.linalg.solve(K, np.vstack([pixels.T, np.ones(20)])).T[:, :2], np.ones(20)])
    camera_points *= rng.uniform(1, 20, size=(20, 1))
    world_points = (camera_points - pose[:3, 3]) @ pose[:3, :3]
    np.testing.assert_allclose(project_blender(scene, obj, world_points), pixels, atol=1e-3)
