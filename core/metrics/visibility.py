"""Which part of a ground-truth surface the training cameras saw.

Recall (the share of the true surface the reconstruction covers) only means something over
the surface the images show: a rover sees a few tens of metres of a terrain mesh that may be
hundreds of metres wide. :func:`visible_surface_samples` marks the surface samples that at
least one camera saw, by a depth test against a z-buffer of the mesh rendered from that
camera (:func:`depth_map`), in plain numpy.

Conventions are COLMAP's (OpenCV's): camera axes x right, y down, z forward; pixel centres
at +0.5. A :class:`CameraView`'s ``world_to_camera`` may be any invertible affine map (a
COLMAP pose composed with the placement of the scene in Blender, scale included): the test
only needs straight lines to stay straight and depth order along a ray to be kept.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Iterable, Optional, Sequence

import numpy as np

#: long side, in pixels, of the z-buffers the visibility test renders (the cameras' own
#: resolution is scaled down to it: occlusion is a coarse question)
DEPTH_MAP_SIZE = 320
#: a sample is visible when its depth is at most the z-buffer's (3x3 neighbourhood maximum)
#: times 1 + this: room for rounding and for the z-buffer's coarse pixels
DEPTH_TOLERANCE = 0.01
#: the scene-scaled match threshold: this share of the median camera-to-surface distance
THRESHOLD_SHARE_OF_VIEWING_DISTANCE = 0.01
#: without cameras: this share of the diagonal of the mesh's bounding box
THRESHOLD_SHARE_OF_MESH_DIAGONAL = 0.005

_CHUNK_PIXELS = 4_000_000  # triangle/pixel pairs tested at once by the rasterizer


@dataclasses.dataclass(frozen=True)
class CameraView:
    """A pinhole camera: pose, intrinsics (pixels) and image size.

    ``world_to_camera``: [4, 4] from the frame of the mesh and samples to the camera's axes
    (x right, y down, z forward). Distortion is ignored: only the frustum and occlusion matter.
    """

    world_to_camera: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    name: str = ""

    @property
    def center(self) -> np.ndarray:
        """[3] the camera centre in the world frame."""
        return np.linalg.solve(np.asarray(self.world_to_camera, dtype=np.float64), [0.0, 0.0, 0.0, 1.0])[:3]

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] world points in the camera's axes."""
        matrix = np.asarray(self.world_to_camera, dtype=np.float64)
        return points @ matrix[:3, :3].T + matrix[:3, 3]


def cameras_from_colmap(model: Any, names: Optional[Iterable[str]] = None,
                        world_from_model: Optional[np.ndarray] = None) -> list[CameraView]:
    """:class:`CameraView` of the images of a COLMAP model (all, or those named).

    ``world_from_model``: [4, 4] placement of the model in the world the mesh lives in (e.g.
    a Blender object's ``matrix_world``); None: the model's own frame.
    """
    wanted = None if names is None else set(names)
    model_from_world = np.eye(4) if world_from_model is None else np.linalg.inv(np.asarray(world_from_model, float))
    views = []
    for image in model.sorted_images():
        if wanted is not None and image.name not in wanted:
            continue
        camera = model.cameras[image.camera_id]
        fx, fy, cx, cy = camera.intrinsics()
        views.append(CameraView(image.world_to_camera() @ model_from_world, float(fx), float(fy), float(cx), float(cy),
                                int(camera.width), int(camera.height), image.name))
    return views


def training_image_names(names: Sequence[str], test_every: int) -> list[str]:
    """The training split of 3DGS (and of :mod:`esgs.core.train.dataset`): images sorted by
    name, index % ``test_every`` == 0 held out; ``test_every`` <= 0 keeps every image."""
    ordered = sorted(names)
    if test_every <= 0:
        return ordered
    return [name for index, name in enumerate(ordered) if index % test_every != 0]


# --------------------------------------------------------------------------- z-buffer


def depth_map(vertices: np.ndarray, faces: np.ndarray, camera: CameraView, max_size: int = DEPTH_MAP_SIZE,
              near: Optional[float] = None) -> tuple[np.ndarray, float]:
    """Z-buffer of a triangle mesh seen from ``camera``.

    Args:
        vertices: [V, 3] world; faces: [F, 3] triangles.
        camera: the view; its image is scaled down so its long side is at most ``max_size``.
        near: near plane (camera units); default 1e-6 of the mesh's extent in camera units.

    Returns:
        (depth [H, W] float64 camera-axis z of the nearest surface at each pixel centre,
        inf where no triangle covers it; scale: depth-map pixels per camera pixel).

    Triangles crossing the near plane are clipped against it, so a ground mesh that runs
    under and behind the camera still occludes correctly.
    """
    scale = min(1.0, max_size / max(camera.width, camera.height))
    width, height = max(1, math.ceil(camera.width * scale)), max(1, math.ceil(camera.height * scale))
    depth = np.full(height * width, np.inf)
    points = camera.to_camera(np.asarray(vertices, dtype=np.float64))
    if near is None:
        near = 1e-6 * max(float(np.ptp(points, axis=0).max()) if len(points) else 1.0, 1e-12)
    corners = _clip_near(points[np.asarray(faces, dtype=np.int64)], near)  # [T, 3, 3]
    if len(corners) == 0:
        return depth.reshape(height, width), scale
    z = corners[:, :, 2]
    u = (camera.fx * corners[:, :, 0] / z + camera.cx) * scale
    v = (camera.fy * corners[:, :, 1] / z + camera.cy) * scale
    # pixel (i, j) has its centre at (i + 0.5, j + 0.5): the columns whose centres the box spans
    i0 = np.maximum(np.ceil(u.min(axis=1) - 0.5), 0).astype(np.int64)
    i1 = np.minimum(np.floor(u.max(axis=1) - 0.5), width - 1).astype(np.int64)
    j0 = np.maximum(np.ceil(v.min(axis=1) - 0.5), 0).astype(np.int64)
    j1 = np.minimum(np.floor(v.max(axis=1) - 0.5), height - 1).astype(np.int64)
    area = (u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (u[:, 2] - u[:, 0]) * (v[:, 1] - v[:, 0])
    keep = (i1 >= i0) & (j1 >= j0) & (np.abs(area) > 0)
    span = np.maximum(i1 - i0, j1 - j0) + 1
    # triangles grouped by the power of two above their box size: one offset grid per group
    size_class = np.ceil(np.log2(np.maximum(span, 1))).astype(np.int64)
    for level in np.unique(size_class[keep]):
        members = np.flatnonzero(keep & (size_class == level))
        side = 1 << int(level)
        dj, di = np.divmod(np.arange(side * side), side)
        per_chunk = max(1, _CHUNK_PIXELS // (side * side))
        for start in range(0, len(members), per_chunk):
            rows = members[start:start + per_chunk]
            column = i0[rows, None] + di[None, :]
            row = j0[rows, None] + dj[None, :]
            inside_box = (column <= i1[rows, None]) & (row <= j1[rows, None])
            px, py = column + 0.5, row + 0.5
            uu, vv, zz = u[rows], v[rows], z[rows]
            # barycentric weights from edge functions, normalised by the signed area
            w0 = ((uu[:, 1, None] - px) * (vv[:, 2, None] - py) - (uu[:, 2, None] - px) * (vv[:, 1, None] - py))
            w1 = ((uu[:, 2, None] - px) * (vv[:, 0, None] - py) - (uu[:, 0, None] - px) * (vv[:, 2, None] - py))
            w0, w1 = w0 / area[rows, None], w1 / area[rows, None]
            w2 = 1.0 - w0 - w1
            eps = -1e-9  # shared edges: a pixel centre on an edge belongs to both triangles
            covered = inside_box & (w0 >= eps) & (w1 >= eps) & (w2 >= eps)
            # 1/z is linear in screen space
            inverse_z = w0 / zz[:, 0, None] + w1 / zz[:, 1, None] + w2 / zz[:, 2, None]
            index = (row * width + column)[covered]
            np.minimum.at(depth, index, 1.0 / inverse_z[covered])
    return depth.reshape(height, width), scale


def _clip_near(corners: np.ndarray, near: float) -> np.ndarray:
    """Triangles [T, 3, 3] (camera axes) clipped against z = near: [T', 3, 3] all in front."""
    in_front = corners[:, :, 2] > near
    count = in_front.sum(axis=1)
    parts = [corners[count == 3]]
    for inside_count in (1, 2):
        group = corners[count == inside_count]
        if len(group) == 0:
            continue
        flags = in_front[count == inside_count]
        # rotate each triangle so its odd vertex (the one inside, or the one outside) comes first
        odd = np.argmax(flags if inside_count == 1 else ~flags, axis=1)
        order = (odd[:, None] + np.arange(3)[None, :]) % 3
        tri = np.take_along_axis(group, order[:, :, None], axis=1)
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        ab, ac = _near_crossing(a, b, near), _near_crossing(a, c, near)
        if inside_count == 1:  # a in front: the corner (a, a->b, a->c)
            parts.append(np.stack([a, ab, ac], axis=1))
        else:  # a behind: the quad (a->b, b, c, a->c) as two triangles
            parts.append(np.stack([ab, b, c], axis=1))
            parts.append(np.stack([ab, c, ac], axis=1))
    return np.concatenate(parts, axis=0)


def _near_crossing(start: np.ndarray, end: np.ndarray, near: float) -> np.ndarray:
    t = (near - start[:, 2]) / (end[:, 2] - start[:, 2])
    point = start + (end - start) * t[:, None]
    point[:, 2] = near
    return point


def _neighbourhood_max(depth: np.ndarray) -> np.ndarray:
    padded = np.pad(depth, 1, mode="edge")
    height, width = depth.shape
    return np.max([padded[dy:dy + height, dx:dx + width] for dy in range(3) for dx in range(3)], axis=0)


# --------------------------------------------------------------------------- visibility


def sample_visibility(vertices: np.ndarray, faces: np.ndarray, samples: np.ndarray, cameras: Sequence[CameraView],
                      *, max_size: int = DEPTH_MAP_SIZE,
                      tolerance: float = DEPTH_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """Which surface samples the cameras saw, and from how far.

    Args:
        vertices: [V, 3], faces: [F, 3]: the mesh the samples lie on (it occludes them).
        samples: [M, 3] points on that mesh's surface, same frame.
        cameras: the views.
        max_size: long side of the z-buffers (see :func:`depth_map`).
        tolerance: relative depth slack of the test.

    Returns:
        (visible [M] bool, distance [M] float64: distance from the nearest camera centre that
        sees the sample, inf where none does).

    A sample is seen by a camera when it lies in front of it (z > 0), projects inside its
    image, and is not occluded: its depth is at most ``1 + tolerance`` times the largest
    z-buffer depth in the 3x3 pixels around its projection. Taking the neighbourhood's
    largest depth keeps samples on steep or grazing surfaces (whose depth changes a lot
    within one coarse pixel); the price is that samples hidden less than one z-buffer pixel
    behind an occluder's silhouette count as seen.
    """
    samples = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
    visible = np.zeros(len(samples), dtype=bool)
    distance = np.full(len(samples), np.inf)
    for camera in cameras:
        local = camera.to_camera(samples)
        z = local[:, 2]
        front = z > 0
        if not front.any():
            continue
        depth, scale = depth_map(vertices, faces, camera, max_size=max_size)
        height, width = depth.shape
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (camera.fx * local[:, 0] / z + camera.cx) * scale
            v = (camera.fy * local[:, 1] / z + camera.cy) * scale
        in_image = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        rows = np.flatnonzero(in_image)
        if len(rows) == 0:
            continue
        column = np.minimum(u[rows].astype(np.int64), width - 1)
        row = np.minimum(v[rows].astype(np.int64), height - 1)
        farthest = _neighbourhood_max(depth)[row, column]
        seen = rows[z[rows] <= farthest * (1.0 + tolerance)]
        visible[seen] = True
        distance[seen] = np.minimum(distance[seen], np.linalg.norm(samples[seen] - camera.center, axis=1))
    return visible, distance


def visible_surface_samples(vertices: np.ndarray, faces: np.ndarray, samples: np.ndarray,
                            cameras: Sequence[CameraView], **options: Any) -> np.ndarray:
    """[M] bool: the surface samples [M, 3] that at least one camera saw.

    A sample counts when it is inside a camera's frustum, in front of it, and not hidden by
    the mesh (``vertices`` [V, 3], ``faces`` [F, 3]) itself: see :func:`sample_visibility`
    for the depth test and ``options`` (``max_size``, ``tolerance``).
    """
    return sample_visibility(vertices, faces, samples, cameras, **options)[0]


def scene_threshold(viewing_distances: Optional[np.ndarray] = None,
                    vertices: Optional[np.ndarray] = None) -> tuple[float, str]:
    """The match distance of precision / recall that scales with the scene, and its rule.

    With cameras: 1 % of the median distance from the training cameras to the surface they
    see (``viewing_distances`` [M], inf entries ignored), about a few pixel footprints for
    usual fields of view. Without: 0.5 % of the diagonal of the mesh's bounding box.
    """
    if viewing_distances is not None:
        finite = np.asarray(viewing_distances, dtype=np.float64)
        finite = finite[np.isfinite(finite)]
        if len(finite):
            share = THRESHOLD_SHARE_OF_VIEWING_DISTANCE
            return float(share * np.median(finite)), \
                f"{share:.0%} of the median camera-to-surface distance ({np.median(finite):.4g})"
    if vertices is None or len(vertices) == 0:
        raise ValueError("scene_threshold needs viewing distances or the mesh's vertices")
    vertices = np.asarray(vertices, dtype=np.float64)
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    share = THRESHOLD_SHARE_OF_MESH_DIAGONAL
    return share * diagonal, f"{share:.1%} of the mesh's bounding-box diagonal ({diagonal:.4g})"
