"""Plain dataclasses for a COLMAP sparse model, independent of pycolmap and bpy.

Conventions (COLMAP's, which are OpenCV's): camera axes x right, y down, z forward;
poses are world-to-camera, ``x_cam = R @ x_world + t``; quaternions are (w, x, y, z);
pixel centres sit at +0.5 (the top-left pixel's centre is (0.5, 0.5)).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Camera:
    """One COLMAP camera.

    ``model`` is a COLMAP model name ("PINHOLE", "SIMPLE_RADIAL", "OPENCV", ...);
    ``params`` are that model's parameters in COLMAP's order.
    """

    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # [P] float64

    @property
    def is_pinhole(self) -> bool:
        """True for models without distortion (SIMPLE_PINHOLE, PINHOLE)."""
        return self.model in ("SIMPLE_PINHOLE", "PINHOLE")

    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of the model's pinhole part, whatever its distortion."""
        from .camera_models import pinhole_part

        return pinhole_part(self.model, self.params)

    def K(self) -> np.ndarray:
        """[3, 3] intrinsic matrix of the pinhole part."""
        fx, fy, cx, cy = self.intrinsics()
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


@dataclass
class Image:
    """One registered image: its world-to-camera pose and its 2D observations."""

    image_id: int
    name: str
    camera_id: int
    quat_wxyz: np.ndarray  # [4] world-to-camera rotation
    translation: np.ndarray  # [3] world-to-camera translation
    points2d: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [M, 2] pixels
    point3d_ids: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))  # [M], -1 = none

    def rotation_matrix(self) -> np.ndarray:
        """[3, 3] world-to-camera rotation."""
        from .geometry import quat_wxyz_to_matrix

        return quat_wxyz_to_matrix(self.quat_wxyz)

    def world_to_camera(self) -> np.ndarray:
        """[4, 4] world-to-camera matrix (OpenCV axes)."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.rotation_matrix()
        matrix[:3, 3] = self.translation
        return matrix

    def camera_center(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        rotation = self.rotation_matrix()
        return -rotation.T @ np.asarray(self.translation, dtype=np.float64)


@dataclass
class Point3D:
    """A triangulated point and its track."""

    point3d_id: int
    xyz: np.ndarray  # [3]
    rgb: np.ndarray  # [3] uint8
    error: float
    track_image_ids: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))
    track_point2d_idxs: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))

    @property
    def track_length(self) -> int:
        return int(len(self.track_image_ids))


@dataclass
class ColmapModel:
    """A whole sparse model. Dicts are keyed by COLMAP ids."""

    cameras: dict[int, Camera]
    images: dict[int, Image]
    points: dict[int, Point3D]
    source: str = ""  # the folder it was read from, for error messages

    def sorted_images(self) -> list[Image]:
        """Images sorted by name (the order 3DGS uses for its train/test split)."""
        return sorted(self.images.values(), key=lambda image: image.name)

    def observed_points(self, image_id: int, *, max_error_px: float = 2.0,
                        min_track_length: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """The 3D points image ``image_id`` observes: (xyz [M,3] float64 world, keypoints [M,2] pixels).

        Only points with reprojection error <= ``max_error_px`` and a track of at least
        ``min_track_length`` images count (single-view or badly fitted points are noise).
        """
        image = self.images[image_id]
        xyz, keypoints = [], []
        for keypoint, point_id in zip(image.points2d, image.point3d_ids):
            point = self.points.get(int(point_id)) if point_id >= 0 else None
            if point is None or point.error > max_error_px or point.track_length < min_track_length:
                continue
            xyz.append(point.xyz)
            keypoints.append(keypoint)
        if not xyz:
            return np.zeros((0, 3)), np.zeros((0, 2))
        return np.asarray(xyz, dtype=np.float64), np.asarray(keypoints, dtype=np.float64)

    def points_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(xyz [P,3] float64, rgb [P,3] uint8, error [P] float64, track_length [P] int64), id order."""
        ids = sorted(self.points)
        if not ids:
            return (np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), np.zeros(0, np.int64))
        xyz = np.stack([self.points[i].xyz for i in ids]).astype(np.float64)
        rgb = np.stack([self.points[i].rgb for i in ids]).astype(np.uint8)
        error = np.array([self.points[i].error for i in ids], dtype=np.float64)
        track = np.array([self.points[i].track_length for i in ids], dtype=np.int64)
        return xyz, rgb, error, track
