"""Scene folders from real images: SfM (pycolmap), panorama cutting, rotation-only stations.

Public API:

- ``scene_from_images(images_dir, out_dir, options, progress) -> report``: pycolmap SfM.
- ``scene_from_panorama(panorama, out_dir, options, progress) -> report``: pinhole views
  (and their known rotation-only cameras) from an equirectangular panorama, or crops of a strip.
- ``scene_from_rotation_only(images_dir, out_dir, options, progress) -> report``: one camera
  station, rotations and a shared focal length estimated from feature matches.
"""
from .panorama import PanoramaOptions, equirectangular_directions, panorama_views, scene_from_panorama
from .rotation import RotationOnlyOptions, estimate_rotations, scene_from_rotation_only
from .sfm import SfmOptions, scene_from_images  # noqa: E402

__all__ = [
    "PanoramaOptions",
    "RotationOnlyOptions",
    "SfmOptions",
    "equirectangular_directions",
    "estimate_rotations",
    "panorama_views",
    "scene_from_images",
    "scene_from_panorama",
    "scene_from_rotation_only",
]
