"""Estimate a rigid transform that makes an SfM scene's ground horizontal with +Z up.

SfM reconstructions come out in an arbitrary frame. Two cues give "up":
- cameras are usually held upright, so the mean of their up vectors (OpenCV -y in world
  coordinates) points roughly up, but tilted cameras (oblique drone or rover views) bias it;
- the sparse points of a terrain scene lie near a ground surface, whose plane normal is
  up up to its sign.
The plane normal (robust least-squares fit) gives the direction, the cameras' mean up
vector gives its sign; with too few points or no dominant plane, the cameras' up alone.

Plain numpy: no bpy needed.
"""
from __future__ import annotations

import numpy as np

# the smallest spread of the points must be this much below the middle one for a plane
_PLANE_RATIO = 0.5


def camera_up_vectors(world_to_camera: np.ndarray) -> np.ndarray:
    """[C, 4, 4] world-to-camera (OpenCV axes) -> [C, 3] unit up vectors in world coordinates."""
    rotations = np.asarray(world_to_camera, dtype=np.float64)[:, :3, :3]
    # camera -y axis expressed in the world: R^T @ (0, -1, 0) = -(row 1 of R)
    return -rotations[:, 1, :]


def fit_plane(points: np.ndarray, iterations: int = 3) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Robust plane fit. points: [N, 3] -> (unit normal [3], centroid [3], flatness) or None.

    Refits after dropping points farther than 2.5 median absolute residuals, so buildings,
    rocks or outliers do not tilt the ground. ``flatness`` is the smallest over the middle
    singular value (0 = perfectly flat).
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 3:
        return None
    inliers = points
    normal = centroid = None
    flatness = 1.0
    for _ in range(iterations):
        if len(inliers) < 3:
            break
        centroid = inliers.mean(axis=0)  # the least-squares plane passes through the mean
        centred = inliers - centroid
        _, singular, vt = np.linalg.svd(centred, full_matrices=False)
        normal = vt[2]
        flatness = float(singular[2] / max(singular[1], 1e-12))
        residuals = np.abs((points - centroid) @ normal)
        limit = 2.5 * max(np.median(residuals), 1e-12)
        inliers = points[residuals <= limit]
    if normal is None:
        return None
    return normal, centroid, flatness


def rotation_between(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[3, 3] smallest rotation taking unit vector ``source`` onto unit vector ``target``."""
    source = source / np.linalg.norm(source)
    target = target / np.linalg.norm(target)
    axis = np.cross(source, target)
    sine = np.linalg.norm(axis)
    cosine = float(np.dot(source, target))
    if sine < 1e-12:
        if cosine > 0:
            return np.eye(3)
        # opposite: rotate 180 degrees about any axis perpendicular to source
        helper = np.array([1.0, 0.0, 0.0]) if abs(source[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        axis = np.cross(source, helper)
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    axis /= sine
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.arctan2(sine, cosine)
    return np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew


def estimate_up(world_to_camera: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
    """[3] unit "up" of the scene from cameras ([C, 4, 4]) and optional points ([N, 3])."""
    camera_up = camera_up_vectors(world_to_camera).mean(axis=0)
    norm = np.linalg.norm(camera_up)
    camera_up = camera_up / norm if norm > 1e-9 else np.array([0.0, 0.0, 1.0])
    if points is not None and len(points) >= 10:
        fit = fit_plane(points)
        if fit is not None and fit[2] < _PLANE_RATIO:
            normal = fit[0]
            return normal if np.dot(normal, camera_up) >= 0 else -normal
    return camera_up


def up_alignment_transform(world_to_camera: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
    """[4, 4] rigid transform (new world from SfM world): estimated up -> +Z, ground at z = 0.

    The points' median (in the levelled frame) moves to the origin, so the ground sits at
    z = 0; without points, the cameras' median does. Scale is unchanged.
    """
    world_to_camera = np.asarray(world_to_camera, dtype=np.float64)
    up = estimate_up(world_to_camera, points)
    rotation = rotation_between(up, np.array([0.0, 0.0, 1.0]))
    if points is not None and len(points) > 0:
        anchors = np.asarray(points, dtype=np.float64)
    else:
        rotations = world_to_camera[:, :3, :3]
        anchors = -np.einsum("cji,cj->ci", rotations, world_to_camera[:, :3, 3])
    # median in the levelled frame: ground height and centre, robust to outliers
    anchor = np.median(anchors @ rotation.T, axis=0)
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = -anchor
    return transform
