"""Blender cameras <-> OpenCV/COLMAP pinhole cameras.

Conventions on the OpenCV side (COLMAP's too): camera axes x right, y down, z forward;
``world_to_camera`` maps world points into those axes; pixel coordinates have their origin
at the top-left corner of the image, so the top-left pixel's centre is (0.5, 0.5), and
``u = fx * x / z + cx``, ``v = fy * y / z + cy``.

Blender's side: a camera looks down its local -Z with +Y up. Blender projects through a
view plane computed from the lens, the sensor size and fit, the lens shift and the scene's
resolution and pixel aspect (``BKE_camera_params_compute_viewplane``). In pixels of a
``width x height`` render, with ``ycor = pixel_aspect_y / pixel_aspect_x`` and
``viewfac = width`` (horizontal fit) or ``ycor * height`` (vertical fit)::

    fx = lens * viewfac / sensor           cx = width / 2 - shift_x * viewfac
    fy = fx / ycor                         cy = height / 2 + shift_y * viewfac / ycor

(``cy`` measured from the top edge, as COLMAP does.) These formulas are inverted exactly
here; Blender stores lens, shifts, pixel aspect and object matrices as 32-bit floats, so
the exact double-precision OpenCV parameters are also kept as custom properties on the
object and returned by :func:`opencv_from_camera_object` while the Blender camera still
agrees with them (nobody edited it since).
"""
from __future__ import annotations

import bpy
import numpy as np
from mathutils import Matrix

from ..core.errors import ConfigError

# OpenCV camera axes -> Blender camera axes (flip y and z); its own inverse
OPENCV_TO_BLENDER_AXES = np.diag([1.0, -1.0, -1.0, 1.0])

SENSOR_SIZE_MM = 36.0

# Custom properties holding the exact parameters (float64 ID properties)
PROP_K = "esgs_opencv_K"
PROP_WORLD_TO_CAMERA = "esgs_opencv_world_to_camera"
PROP_SIZE = "esgs_opencv_size"

# How far the 32-bit Blender state may drift from the stored exact parameters and still be
# "the same camera": float32 keeps ~7 significant digits, a few operations lose a few ulps.
_RELATIVE_TOLERANCE = 2e-5


def pixel_aspect_from_focal(fx: float, fy: float) -> tuple[float, float]:
    """(pixel_aspect_x, pixel_aspect_y) making Blender's fy / fx equal the given ratio.

    Blender keeps both values >= 1, so the smaller one is 1.
    """
    if fy >= fx:
        return float(fy / fx), 1.0
    return 1.0, float(fx / fy)


def _check_intrinsics(K: np.ndarray, width: int, height: int) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ConfigError(f"intrinsic matrix must be 3x3, got shape {K.shape}")
    if width <= 0 or height <= 0:
        raise ConfigError(f"image size must be positive, got {width}x{height}")
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.all(np.isfinite(K))):
        raise ConfigError(f"focal lengths must be positive and finite, got fx={K[0, 0]}, fy={K[1, 1]}")
    if abs(K[0, 1]) > 1e-9 * K[0, 0]:
        raise ConfigError(
            f"intrinsic matrix has skew {K[0, 1]}; Blender cameras cannot represent it",
            hint="undistort/rectify the images to a pinhole model without skew first",
        )
    return K


def _check_pose(world_to_camera: np.ndarray) -> np.ndarray:
    matrix = np.asarray(world_to_camera, dtype=np.float64)
    if matrix.shape != (4, 4):
        raise ConfigError(f"world_to_camera must be 4x4, got shape {matrix.shape}")
    rotation = matrix[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6) or np.linalg.det(rotation) < 0:
        raise ConfigError("world_to_camera's 3x3 part is not a rotation (orthonormal, det +1)")
    return matrix


def _sensor_fit_for(width: float, height: float, pixel_aspect_x: float, pixel_aspect_y: float) -> str:
    """The fit Blender's AUTO would pick: the axis that is longer once pixel aspect is applied."""
    return "HORIZONTAL" if pixel_aspect_x * width >= pixel_aspect_y * height else "VERTICAL"


def apply_intrinsics(camera_data: bpy.types.Camera, K: np.ndarray, width: int, height: int) -> None:
    """Set lens, sensor, sensor fit and shift of ``camera_data`` for ``K`` ([3, 3]) at ``width x height``.

    Assumes the scene renders at ``width x height`` with the pixel aspect of
    :func:`pixel_aspect_from_focal` (see :func:`set_scene_resolution_from_camera`).
    """
    K = _check_intrinsics(K, width, height)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    aspect_x, aspect_y = pixel_aspect_from_focal(fx, fy)
    ycor = aspect_y / aspect_x
    fit = _sensor_fit_for(width, height, aspect_x, aspect_y)
    viewfac = width if fit == "HORIZONTAL" else ycor * height
    camera_data.type = "PERSP"
    camera_data.lens_unit = "MILLIMETERS"
    camera_data.sensor_fit = fit
    camera_data.sensor_width = SENSOR_SIZE_MM
    # Blender reads sensor_height only with a vertical fit; keep it consistent for display
    camera_data.sensor_height = SENSOR_SIZE_MM if fit == "VERTICAL" else SENSOR_SIZE_MM * ycor * height / width
    camera_data.lens = fx * SENSOR_SIZE_MM / viewfac
    camera_data.shift_x = (width / 2.0 - cx) / viewfac
    camera_data.shift_y = (cy - height / 2.0) * ycor / viewfac


def blender_matrix_world_from_opencv(world_to_camera: np.ndarray) -> np.ndarray:
    """[4, 4] OpenCV world-to-camera -> [4, 4] Blender camera object ``matrix_world``."""
    return np.linalg.inv(_check_pose(world_to_camera)) @ OPENCV_TO_BLENDER_AXES


def opencv_world_to_camera_from_blender(matrix_world: np.ndarray) -> np.ndarray:
    """[4, 4] Blender camera ``matrix_world`` (scale ignored) -> [4, 4] OpenCV world-to-camera."""
    matrix = np.array(matrix_world, dtype=np.float64)
    rotation = matrix[:3, :3]
    # Blender normalises the camera matrix before projecting, so object scale is ignored;
    # re-orthonormalise (SVD) to remove both scale and float32 noise.
    u, _, vt = np.linalg.svd(rotation)
    rotation = u @ vt
    camera_to_world = np.eye(4)
    camera_to_world[:3, :3] = rotation
    camera_to_world[:3, 3] = matrix[:3, 3]
    camera_to_world = camera_to_world @ OPENCV_TO_BLENDER_AXES
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = camera_to_world[:3, :3].T
    world_to_camera[:3, 3] = -camera_to_world[:3, :3].T @ camera_to_world[:3, 3]
    return world_to_camera


def camera_object_from_opencv(
    name: str,
    K: np.ndarray,
    world_to_camera: np.ndarray,
    width: int,
    height: int,
    collection: bpy.types.Collection | None = None,
) -> bpy.types.Object:
    """Create a Blender camera object that sees exactly what the OpenCV camera sees.

    K: [3, 3] intrinsics in pixels (no skew); world_to_camera: [4, 4] (OpenCV axes);
    width, height: image size in pixels. The object is linked to ``collection`` (default:
    the active scene's collection). The scene's resolution and pixel aspect are NOT
    changed; call :func:`set_scene_resolution_from_camera` for the camera you render with.
    """
    K = _check_intrinsics(K, width, height)
    world_to_camera = _check_pose(world_to_camera)
    camera_data = bpy.data.cameras.new(name)
    try:
        apply_intrinsics(camera_data, K, width, height)
        obj = bpy.data.objects.new(name, camera_data)
    except Exception:
        bpy.data.cameras.remove(camera_data)
        raise
    obj.rotation_mode = "QUATERNION"
    obj.matrix_world = Matrix(blender_matrix_world_from_opencv(world_to_camera).tolist())
    obj[PROP_K] = [float(v) for v in K.reshape(-1)]
    obj[PROP_WORLD_TO_CAMERA] = [float(v) for v in world_to_camera.reshape(-1)]
    obj[PROP_SIZE] = [int(width), int(height)]
    if collection is None:
        collection = bpy.context.scene.collection
    collection.objects.link(obj)
    return obj


def set_scene_resolution_from_camera(scene: bpy.types.Scene, width: int, height: int, fx: float, fy: float) -> None:
    """Render ``scene`` at ``width x height`` (100 %) with the pixel aspect that gives fy / fx."""
    if width <= 0 or height <= 0:
        raise ConfigError(f"image size must be positive, got {width}x{height}")
    aspect_x, aspect_y = pixel_aspect_from_focal(fx, fy)
    render = scene.render
    render.resolution_x = int(width)
    render.resolution_y = int(height)
    render.resolution_percentage = 100
    render.pixel_aspect_x = aspect_x
    render.pixel_aspect_y = aspect_y


def use_camera(scene: bpy.types.Scene, obj: bpy.types.Object) -> None:
    """Make ``obj`` the scene camera and, for a camera made by :func:`camera_object_from_opencv`,
    set the render resolution and pixel aspect it was made for (models with several sizes)."""
    if obj.type != "CAMERA":
        raise ConfigError(f"object '{obj.name}' is a {obj.type}, not a camera")
    stored = _stored_parameters(obj)
    if stored is not None:
        K, _, (width, height) = stored
        set_scene_resolution_from_camera(scene, width, height, K[0, 0], K[1, 1])
    scene.camera = obj


def render_size(scene: bpy.types.Scene) -> tuple[int, int]:
    """The rendered image size in pixels (resolution times percentage, as Blender rounds it)."""
    render = scene.render
    # Blender: (resolution * percentage) / 100 in integer arithmetic
    width = (render.resolution_x * render.resolution_percentage) // 100
    height = (render.resolution_y * render.resolution_percentage) // 100
    return int(width), int(height)


def intrinsics_from_blender(camera_data: bpy.types.Camera, scene: bpy.types.Scene) -> np.ndarray:
    """[3, 3] K in pixels of the scene's render size, computed from Blender's camera settings."""
    if camera_data.type != "PERSP":
        raise ConfigError(
            f"camera '{camera_data.name}' is {camera_data.type}; only perspective cameras map to COLMAP",
            hint="set the camera type to Perspective",
        )
    width, height = render_size(scene)
    aspect_x = float(scene.render.pixel_aspect_x)
    aspect_y = float(scene.render.pixel_aspect_y)
    ycor = aspect_y / aspect_x
    fit = camera_data.sensor_fit
    if fit == "AUTO":
        sensor = camera_data.sensor_width
        fit = _sensor_fit_for(width, height, aspect_x, aspect_y)
    else:
        sensor = camera_data.sensor_width if fit == "HORIZONTAL" else camera_data.sensor_height
    viewfac = width if fit == "HORIZONTAL" else ycor * height
    fx = camera_data.lens * viewfac / sensor
    fy = fx / ycor
    cx = width / 2.0 - camera_data.shift_x * viewfac
    cy = height / 2.0 + camera_data.shift_y * viewfac / ycor
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _stored_parameters(obj: bpy.types.Object) -> tuple[np.ndarray, np.ndarray, tuple[int, int]] | None:
    try:
        K = np.array(obj[PROP_K], dtype=np.float64).reshape(3, 3)
        world_to_camera = np.array(obj[PROP_WORLD_TO_CAMERA], dtype=np.float64).reshape(4, 4)
        width, height = (int(v) for v in obj[PROP_SIZE])
    except (KeyError, ValueError, TypeError):
        return None
    return K, world_to_camera, (width, height)


def _agree(computed: np.ndarray, stored: np.ndarray, scale: float) -> bool:
    return bool(np.all(np.abs(computed - stored) <= _RELATIVE_TOLERANCE * scale))


def opencv_from_camera_object(
    obj: bpy.types.Object, scene: bpy.types.Scene
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(K [3, 3], world_to_camera [4, 4], width, height) of a Blender camera object.

    Uses the scene's resolution, resolution percentage and pixel aspect, the camera's lens,
    sensor, fit and shift, and the object's world matrix. When the result matches (to 32-bit
    precision) the exact parameters stored by :func:`camera_object_from_opencv`, those exact
    float64 values are returned instead, so an import/export round trip is lossless.
    """
    if obj.type != "CAMERA":
        raise ConfigError(f"object '{obj.name}' is a {obj.type}, not a camera")
    K = intrinsics_from_blender(obj.data, scene)
    world_to_camera = opencv_world_to_camera_from_blender(np.array(obj.matrix_world))
    width, height = render_size(scene)
    stored = _stored_parameters(obj)
    if stored is not None:
        stored_K, stored_pose, stored_size = stored
        translation_scale = 1.0 + float(np.abs(stored_pose[:3, 3]).max()) + float(np.abs(obj.matrix_world.translation).max())
        if (
            stored_size == (width, height)
            and _agree(K, stored_K, float(max(width, height, K[0, 0], K[1, 1])))
            and _agree(world_to_camera[:3, :3], stored_pose[:3, :3], 1.0)
            and _agree(world_to_camera[:3, 3], stored_pose[:3, 3], translation_scale)
        ):
            return stored_K.copy(), stored_pose.copy(), width, height
    return K, world_to_camera, width, height
