"""Hand-built COLMAP scenes for the Blender-side tests (synthetic models, the shared real one)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from esgs.core.colmap.geometry import matrix_to_quat_wxyz
from esgs.core.colmap.io import write_model
from esgs.core.colmap.model import Camera, ColmapModel, Image, Point3D
from tests.conftest import require_shared


def maupertuis_scene(tmp_path: Path) -> Path:
    """A scene folder (images/ + sparse/0) pointing at the shared model by symlinks."""
    data = require_shared("colmap_maupertuis")
    scene = tmp_path / "maupertuis"
    (scene / "sparse").mkdir(parents=True)
    os.symlink(data / "images", scene / "images")
    os.symlink(data / "sparse_bin", scene / "sparse" / "0")
    return scene


def look_at(centre: np.ndarray, target: np.ndarray, down_hint=np.array([0.0, 0.0, -1.0])) -> np.ndarray:
    """[4, 4] OpenCV world-to-camera looking from ``centre`` at ``target``."""
    forward = target - centre
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, -down_hint)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = -rotation @ centre
    return matrix


def synthetic_model(
    sizes=((640, 480), (360, 720)),
    model_name="PINHOLE",
    extra_params=(),
    ground_rotation: np.ndarray | None = None,
    seed: int = 0,
) -> ColmapModel:
    """Cameras circling a bumpy ground patch; points observed by every camera that sees them.

    PINHOLE cameras with fx != fy and an off-centre principal point, one landscape and one
    portrait size. ``ground_rotation`` tilts the whole scene (to test orient_up).
    """
    rng = np.random.default_rng(seed)
    tilt = np.eye(3) if ground_rotation is None else ground_rotation
    model_cameras = {}
    for index, (width, height) in enumerate(sizes, start=1):
        fx, fy = 0.9 * max(width, height), 0.95 * max(width, height)
        cx, cy = 0.46 * width, 0.53 * height
        if model_name == "PINHOLE":
            params = [fx, fy, cx, cy]
        elif model_name in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL"):
            params = [fx, cx, cy]
        else:
            params = [fx, fy, cx, cy]
        model_cameras[index] = Camera(index, model_name, width, height, np.array(params + list(extra_params), float))
    xy = rng.uniform(-4, 4, size=(300, 2))
    ground = np.column_stack([xy, 0.05 * rng.normal(size=300)]) @ tilt.T
    images = {}
    observations: dict[int, list[tuple[int, int]]] = {i: [] for i in range(len(ground))}
    for image_id in range(1, 9):
        angle = 2 * np.pi * image_id / 8
        centre = np.array([9 * np.cos(angle), 9 * np.sin(angle), 5.0 + 0.3 * image_id]) @ tilt.T
        pose = look_at(centre, np.array([0.3, -0.2, 0.0]) @ tilt.T, down_hint=tilt @ np.array([0.0, 0.0, -1.0]))
        camera = model_cameras[1 + image_id % len(model_cameras)]
        K = camera.K()
        camera_points = ground @ pose[:3, :3].T + pose[:3, 3]
        pixels = camera_points @ K.T
        pixels = pixels[:, :2] / pixels[:, 2:3]
        visible = np.flatnonzero(
            (camera_points[:, 2] > 0)
            & (pixels[:, 0] >= 0) & (pixels[:, 0] < camera.width)
            & (pixels[:, 1] >= 0) & (pixels[:, 1] < camera.height)
        )
        ids = visible + 1
        for point2d_idx, point_index in enumerate(visible):
            observations[point_index].append((image_id, point2d_idx))
        images[image_id] = Image(
            image_id, f"view_{image_id:02d}.png", camera.camera_id, matrix_to_quat_wxyz(pose[:3, :3]), pose[:3, 3].copy(),
            points2d=pixels[visible], point3d_ids=ids.astype(np.int64),
        )
    points = {}
    for index, track in observations.items():
        if len(track) < 2:
            continue
        points[index + 1] = Point3D(
            index + 1, ground[index], rng.integers(0, 256, size=3).astype(np.uint8), float(rng.uniform(0.1, 1.0)),
            np.array([t[0] for t in track], dtype=np.int64), np.array([t[1] for t in track], dtype=np.int64),
        )
    # drop observations of points that were not kept (tracks of length 1)
    for image in images.values():
        keep = np.array([pid in points for pid in image.point3d_ids], dtype=bool)
        image.point3d_ids = np.where(keep, image.point3d_ids, -1)
    return ColmapModel(model_cameras, images, points)


def write_scene(tmp_path: Path, model: ColmapModel, name="synthetic") -> Path:
    scene = tmp_path / name
    write_model(model, scene / "sparse" / "0", binary=True)
    (scene / "images").mkdir()
    return scene


def tilt_rotation() -> np.ndarray:
    axis = np.array([0.6, -0.8, 0.0])
    angle = np.radians(35.0)
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew
