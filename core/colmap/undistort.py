"""Undistort images and cameras to the PINHOLE model (what Gaussian splatting expects).

The warp is built from pycolmap's own projection of each camera model, so every model
COLMAP knows (radial, OpenCV, fisheye, FOV, thin prism...) is handled by one code path
and matches COLMAP exactly: for each pixel of the undistorted (pinhole) image, its ray is
projected through the distorted camera with ``pycolmap.Camera.img_from_cam``, and OpenCV's
``remap`` samples the distorted image there.

Pixel convention: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV's
``remap`` at (0, 0); the maps subtract 0.5.
"""
from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..io_utils import atomic_directory
from ..progress import ProgressCallback, ProgressEvent, no_progress
from ..formats.scene_dir import SceneDir
from .camera_models import PINHOLE_MODELS, model_info
from .model import Camera, ColmapModel, Image


def _pycolmap_camera(camera: Camera):
    import pycolmap

    return pycolmap.Camera(
        camera_id=int(camera.camera_id),
        model=camera.model,
        width=int(camera.width),
        height=int(camera.height),
        params=np.asarray(camera.params, dtype=np.float64),
    )


def undistorted_camera(camera: Camera, *, keep_size: bool = False, blank_pixels: float = 0.0) -> Camera:
    """The PINHOLE camera an undistorted image of ``camera`` is taken with.

    With ``keep_size`` the image keeps its width, height and pinhole part (fx, fy, cx, cy);
    corners the distorted image does not cover turn black and strongly distorted borders
    may be cut off. Otherwise COLMAP's undistorter chooses the size and focal lengths so
    that (with ``blank_pixels=0``) every output pixel is covered, as ``colmap
    image_undistorter`` does. Pinhole cameras are returned as PINHOLE with the same numbers.
    """
    info = model_info(camera.model)
    if not info.has_pinhole_part:
        raise DatasetError(
            f"camera {camera.camera_id}: the {info.name} model has no pinhole equivalent",
            hint="convert the images to perspective views first",
        )
    fx, fy, cx, cy = camera.intrinsics()
    if keep_size or camera.model in PINHOLE_MODELS:
        return Camera(camera.camera_id, "PINHOLE", camera.width, camera.height, np.array([fx, fy, cx, cy]))
    import pycolmap

    options = pycolmap.UndistortCameraOptions()
    options.blank_pixels = float(blank_pixels)
    try:
        result = pycolmap.undistort_camera(options, _pycolmap_camera(camera))
    except Exception as error:  # pycolmap raises on degenerate parameters
        raise DatasetError(f"camera {camera.camera_id}: COLMAP cannot undistort it: {error}") from error
    return Camera(camera.camera_id, "PINHOLE", int(result.width), int(result.height), np.asarray(result.params, dtype=np.float64))


def undistortion_maps(camera: Camera, new_camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV remap tables: (map_x, map_y), each [H', W'] float32, for ``cv2.remap``.

    ``map[y, x]`` is where the undistorted pixel (x, y) of ``new_camera`` (a pinhole
    camera) lies in the distorted image of ``camera``, in OpenCV pixel coordinates.
    Rays the distorted model cannot project get -1 (outside: filled with the border value).
    """
    if new_camera.model not in PINHOLE_MODELS:
        raise DatasetError(f"the target camera must be a pinhole model, got {new_camera.model}")
    fx, fy, cx, cy = new_camera.intrinsics()
    columns = (np.arange(new_camera.width, dtype=np.float64) + 0.5 - cx) / fx
    rows = (np.arange(new_camera.height, dtype=np.float64) + 0.5 - cy) / fy
    ray_x, ray_y = np.meshgrid(columns, rows)
    rays = np.stack([ray_x.ravel(), ray_y.ravel(), np.ones(ray_x.size)], axis=1)
    projected = np.asarray(_pycolmap_camera(camera).img_from_cam(rays), dtype=np.float64)
    projected = np.where(np.isfinite(projected), projected - 0.5, -1.0)
    shape = (new_camera.height, new_camera.width)
    return projected[:, 0].reshape(shape).astype(np.float32), projected[:, 1].reshape(shape).astype(np.float32)


def undistort_image(
    image: np.ndarray,
    camera: Camera,
    new_camera: Camera,
    *,
    interpolation: str = "linear",
    maps: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Warp ``image`` ([H, W] or [H, W, C], taken by ``camera``) into ``new_camera``'s view.

    ``interpolation``: "linear" for photographs, "nearest" for masks and label maps,
    "cubic" for the sharpest result. Pass ``maps`` from :func:`undistortion_maps` to reuse
    them across images of one camera. Returns [H', W'] or [H', W', C], same dtype.
    """
    import cv2

    image = np.asarray(image)
    if image.shape[:2] != (camera.height, camera.width):
        raise DatasetError(
            f"image is {image.shape[1]} x {image.shape[0]}, camera {camera.camera_id} is {camera.width} x {camera.height}"
        )
    flags = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST, "cubic": cv2.INTER_CUBIC}.get(interpolation)
    if flags is None:
        raise DatasetError(f"unknown interpolation {interpolation!r}", hint="use linear, nearest or cubic")
    map_x, map_y = maps if maps is not None else undistortion_maps(camera, new_camera)
    return cv2.remap(image, map_x, map_y, flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def undistort_points(points2d: np.ndarray, camera: Camera, new_camera: Camera) -> np.ndarray:
    """Move 2D observations [M, 2] (COLMAP pixels) from ``camera`` to the pinhole ``new_camera``."""
    points2d = np.asarray(points2d, dtype=np.float64).reshape(-1, 2)
    if len(points2d) == 0:
        return points2d.copy()
    normalized = np.asarray(_pycolmap_camera(camera).cam_from_img(points2d), dtype=np.float64)
    fx, fy, cx, cy = new_camera.intrinsics()
    return np.stack([normalized[:, 0] * fx + cx, normalized[:, 1] * fy + cy], axis=1)


def undistort_model(
    model: ColmapModel,
    images_dir: str | Path,
    out_dir: str | Path,
    *,
    keep_size: bool = False,
    blank_pixels: float = 0.0,
    jpeg_quality: int = 95,
    overwrite: bool = False,
    progress: ProgressCallback = no_progress,
) -> ColmapModel:
    """Write an undistorted scene folder: ``out_dir/images/`` and ``out_dir/sparse/0/`` (binary).

    Every camera becomes PINHOLE (see :func:`undistorted_camera` for ``keep_size`` and
    ``blank_pixels``); images keep their names (re-encoded in the same format; images of
    pinhole cameras are copied unchanged) and 2D observations are moved accordingly.
    Poses and 3D points are unchanged. The folder is built atomically. Returns the new model.
    """
    from ..formats.imageio import read_image
    from ..io_utils import atomic_write_bytes
    from .io import write_model
    from .validate import validate_images

    images_dir = Path(images_dir)
    validate_images(model, images_dir)
    new_cameras = {
        camera_id: undistorted_camera(camera, keep_size=keep_size, blank_pixels=blank_pixels)
        for camera_id, camera in model.cameras.items()
    }
    maps: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    new_images: dict[int, Image] = {}
    images = model.sorted_images()
    with atomic_directory(out_dir, overwrite=overwrite) as staging:
        staged = SceneDir(staging)
        staged.images.mkdir()
        for step, image in enumerate(images):
            camera, new_camera = model.cameras[image.camera_id], new_cameras[image.camera_id]
            source, target = images_dir / image.name, staged.image(image.name)
            target.parent.mkdir(parents=True, exist_ok=True)
            if camera.model in PINHOLE_MODELS:
                shutil.copyfile(source, target)
                points2d = image.points2d.copy()
            else:
                if image.camera_id not in maps:
                    maps[image.camera_id] = undistortion_maps(camera, new_camera)
                pixels = read_image(source)
                warped = undistort_image(pixels, camera, new_camera, maps=maps[image.camera_id])
                atomic_write_bytes(target, _encode_like(target, warped, jpeg_quality))
                points2d = undistort_points(image.points2d, camera, new_camera)
            new_images[image.image_id] = replace(image, points2d=points2d, point3d_ids=image.point3d_ids.copy())
            progress(ProgressEvent(step + 1, len(images), stage="undistort"))
        new_model = ColmapModel(new_cameras, new_images, model.points, source=str(SceneDir(out_dir).model))
        write_model(new_model, staged.model, binary=True)
    return new_model


def _encode_like(path: Path, rgb: np.ndarray, jpeg_quality: int) -> bytes:
    """Encode an RGB/grey uint8 array in the format named by ``path``'s extension."""
    import cv2

    array = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if rgb.ndim == 3 else rgb
    extension = path.suffix.lower() or ".png"
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if extension in (".jpg", ".jpeg") else []
    try:
        ok, encoded = cv2.imencode(extension, array, params)
    except cv2.error as error:
        raise DatasetError(f"cannot encode an image as {extension}: {error}", path=path) from error
    if not ok:
        raise DatasetError(f"cannot encode an image as {extension}", path=path)
    return encoded.tobytes()
