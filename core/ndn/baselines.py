"""The sparse-SfM baseline NDN is compared against: triangulated points, interpolated.

For a scene folder with known cameras (``sparse/0``), :func:`triangulate_known_poses` runs
pycolmap's SIFT extraction, exhaustive matching and point triangulation with the poses held
fixed, so the baseline is what real SfM would give on those images (not the exact surface
samples a synthetic scene stores in ``sparse/0``). :func:`sparse_view_depths` turns the
points into per-view observations, :func:`densify_sparse_depth` interpolates them linearly
(nearest value outside their convex hull) and :func:`normals_from_depth` differentiates the
dense depth into camera-frame normals. The other baseline, a regression UNet, is the NDN
network trained with ``--prediction regression`` (see :mod:`.diffusion`).
"""
from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..formats.scene_dir import SceneDir


@dataclass
class SparseDepth:
    """One view's triangulated observations: ``uv`` [K, 2] pixel coordinates in the original
    image (pixel centres at +0.5) and their z depth ``depth`` [K] in scene units."""

    uv: np.ndarray
    depth: np.ndarray


def triangulate_known_poses(scene_dir: str | Path, *, upscale: float = 2.0, peak_threshold: float = 0.004,
                            work_dir: str | Path | None = None) -> dict[str, SparseDepth]:
    """Triangulate SIFT matches of a scene's images with its known cameras; per image name, the
    observed points' pixel positions and depths.

    ``upscale`` enlarges the images before SIFT (small renders yield too few features at their
    own size; 2x and a lower ``peak_threshold`` gave 10-50x more points on 160x90 renders).
    Views without a triangulated point map to empty arrays. The triangulation itself is
    :func:`..colmap.triangulate.triangulate_known_poses`.
    """
    import cv2  # before pycolmap: cv2's PNG writer crashes (zlib clash) when imported after it

    from ..colmap import read_model
    from ..colmap.triangulate import triangulate_known_poses as triangulate_model
    from ..formats.imageio import read_image, write_png

    scene_dir = Path(scene_dir)
    scene = SceneDir(scene_dir)
    model = read_model(scene_dir, use_pycolmap=False)
    if len(model.cameras) != 1:
        raise DatasetError("the SfM baseline expects one camera per scene", path=scene.model)
    camera = next(iter(model.cameras.values()))
    if camera.model != "PINHOLE":
        raise DatasetError(f"the SfM baseline expects a PINHOLE camera, got {camera.model}", path=scene_dir)
    work = Path(tempfile.mkdtemp(prefix="esgs-sfm-baseline-", dir=work_dir))
    try:
        # the upscaled images, laid out as a scene folder's images/ (the poses stay the scene's)
        upscaled = SceneDir(work)
        upscaled.images.mkdir()
        for image in model.images.values():
            rgb = read_image(scene.image(image.name))
            write_png(upscaled.image(image.name),
                      cv2.resize(rgb, None, fx=upscale, fy=upscale, interpolation=cv2.INTER_CUBIC))
        result = triangulate_model(upscaled.images, scene.model,
                                   camera_params=np.asarray(camera.params, float) * upscale,
                                   peak_threshold=peak_threshold, num_threads=1)
        observations: dict[str, tuple[list, list]] = {image.name: ([], []) for image in model.images.values()}
        by_name = {image.name: image for image in model.images.values()}
        for point in result.points3D.values():
            for element in point.track.elements:
                name = result.images[element.image_id].name
                image = by_name[name]
                camera_point = image.rotation_matrix() @ np.asarray(point.xyz, float) + np.asarray(image.translation)
                if camera_point[2] <= 0:
                    continue
                uv = np.asarray(result.images[element.image_id].points2D[element.point2D_idx].xy, float) / upscale
                observations[name][0].append(uv)
                observations[name][1].append(camera_point[2])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return {name: SparseDepth(np.asarray(uv, float).reshape(-1, 2), np.asarray(depth, float))
            for name, (uv, depth) in observations.items()}


def densify_sparse_depth(uv: np.ndarray, depth: np.ndarray, width: int, height: int) -> np.ndarray | None:
    """Dense [height, width] depth from samples at ``uv`` [K, 2] (pixel centres at +0.5):
    linear inside the samples' convex hull, nearest sample outside. None with < 1 sample;
    one or two samples (no hull) give the nearest-sample map."""
    from scipy.interpolate import griddata

    if len(depth) == 0:
        return None
    rows, columns = np.mgrid[0:height, 0:width] + 0.5
    nearest = griddata(uv, depth, (columns, rows), method="nearest")
    if len(depth) < 3:
        return nearest.astype(np.float32)
    try:
        linear = griddata(uv, depth, (columns, rows), method="linear")
    except Exception:  # collinear samples: qhull cannot build a triangulation
        return nearest.astype(np.float32)
    return np.where(np.isfinite(linear), linear, nearest).astype(np.float32)


def normals_from_depth(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Camera-frame unit normals [3, H, W] (OpenCV axes, facing the camera) of a z-depth map
    [H, W] under a pinhole camera: the cross product of the back-projected surface's image
    derivatives."""
    height, width = depth.shape
    rows, columns = np.mgrid[0:height, 0:width] + 0.5
    points = np.stack([(columns - cx) / fx * depth, (rows - cy) / fy * depth, depth], axis=0)
    along_u = np.gradient(points, axis=2)
    along_v = np.gradient(points, axis=1)
    normal = np.cross(along_u, along_v, axis=0)
    facing = np.sign(-(normal * points).sum(axis=0, keepdims=True))  # towards the camera
    normal = normal * np.where(facing == 0, 1.0, facing)
    length = np.linalg.norm(normal, axis=0, keepdims=True)
    return np.where(length > 1e-12, normal / np.maximum(length, 1e-12), np.array([0.0, 0.0, -1.0])[:, None, None])


def sfm_baseline_maps(sparse: SparseDepth, image_size: tuple[int, int], working_size: tuple[int, int],
                      camera_params: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """The baseline's maps of one view at the working size (w, h): (depth [h, w], normals
    [3, h, w], has_points). A view without points gets a constant depth and normals facing the
    camera (what one can say with no information)."""
    width, height = working_size
    scale_x, scale_y = width / image_size[0], height / image_size[1]
    fx, fy, cx, cy = (float(v) for v in camera_params[:4])
    dense = densify_sparse_depth(sparse.uv * [scale_x, scale_y], sparse.depth, width, height)
    if dense is None:
        normals = np.zeros((3, height, width), np.float32)
        normals[2] = -1.0
        return np.ones((height, width), np.float32), normals, False
    normals = normals_from_depth(dense, fx * scale_x, fy * scale_y, cx * scale_x, cy * scale_y)
    return dense, normals.astype(np.float32), True
