"""COLMAP sparse models: the project's own small dataclasses, read by a checked parser, written through pycolmap.

Public API (see :mod:`.model` for the dataclasses):

- ``read_model(path) -> ColmapModel``: text or binary model folder (or a scene folder
  holding ``sparse/0``), validated with clear :class:`~esgs.core.errors.DatasetError`\\ s and read
  once (``use_pycolmap=True``: pycolmap's reading of the same bytes, the tests' cross-check).
- ``write_model(model, path, binary=True)``: atomically.
- ``load_scene(scene_dir) -> (model, images_dir)``: a scene folder (images/ + sparse/0).
- ``validate_images(model, images_dir)``, ``check_image_sizes(model, images_dir)``.
- ``pinhole_part(model_name, params) -> (fx, fy, cx, cy)`` for every COLMAP camera model.
- ``undistort_model(model, images_dir, out_dir)`` and the per-image pieces
  (``undistorted_camera``, ``undistortion_maps``, ``undistort_image``, ``undistort_points``):
  any camera model to PINHOLE.
"""
from .camera_models import CAMERA_MODELS, PINHOLE_MODELS, model_info, pinhole_part
from .io import find_model_dir, from_pycolmap, load_scene, parse_model, read_model, to_pycolmap, write_model
from .model import Camera, ColmapModel, Image, Point3D
from .undistort import undistort_image, undistort_model, undistort_points, undistorted_camera, undistortion_maps
from .validate import check_image_sizes, check_references, validate_images

__all__ = [
    "CAMERA_MODELS",
    "PINHOLE_MODELS",
    "Camera",
    "ColmapModel",
    "Image",
    "Point3D",
    "check_image_sizes",
    "check_references",
    "find_model_dir",
    "from_pycolmap",
    "load_scene",
    "model_info",
    "parse_model",
    "pinhole_part",
    "read_model",
    "to_pycolmap",
    "undistort_image",
    "undistort_model",
    "undistort_points",
    "undistorted_camera",
    "undistortion_maps",
    "validate_images",
    "write_model",
]
