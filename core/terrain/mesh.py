"""Triangle meshes of a terrain: the heightfield grid, and rocks as irregular blobs.

Plain arrays (no bpy, no trimesh) so the Blender scene builder, the ground-truth mesh
export and tests share one geometry. Triangles wind counter-clockwise seen from outside
(from above for the ground), so face normals point out of the surface.
"""
from __future__ import annotations

import functools

import numpy as np

from .heightfield import Terrain


def heightfield_mesh(terrain: Terrain, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Ground mesh: vertices [N, 3] float64 (x, y, z metres), faces [F, 3] int64.

    Vertices are row-major over the (optionally decimated) grid: vertex ``i * C + j`` is
    row ``i`` (along +y), column ``j`` (along +x); ``stride`` keeps every stride-th sample
    and always the last row and column, so the mesh covers the whole square.
    """
    if stride < 1:
        raise ValueError("stride must be >= 1")
    resolution = terrain.resolution
    keep = np.arange(0, resolution, stride)
    if keep[-1] != resolution - 1:
        keep = np.append(keep, resolution - 1)
    x_axis, y_axis = terrain.coordinates
    heights = terrain.heights[np.ix_(keep, keep)].astype(np.float64)
    count = keep.size
    x, y = np.meshgrid(x_axis[keep], y_axis[keep])
    vertices = np.stack([x.ravel(), y.ravel(), heights.ravel()], axis=1)
    rows, cols = np.meshgrid(np.arange(count - 1), np.arange(count - 1), indexing="ij")
    v00 = (rows * count + cols).ravel()
    v01, v10 = v00 + 1, v00 + count
    v11 = v10 + 1
    # (v00 -> +x -> +x+y) and (v00 -> +x+y -> +y): counter-clockwise from above.
    faces = np.concatenate([np.stack([v00, v01, v11], axis=1), np.stack([v00, v11, v10], axis=1)])
    return vertices, faces


@functools.lru_cache(maxsize=8)
def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    golden = (1.0 + 5.0 ** 0.5) / 2.0
    vertices = [(-1, golden, 0), (1, golden, 0), (-1, -golden, 0), (1, -golden, 0),
                (0, -1, golden), (0, 1, golden), (0, -1, -golden), (0, 1, -golden),
                (golden, 0, -1), (golden, 0, 1), (-golden, 0, -1), (-golden, 0, 1)]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
             (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
             (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    points = [np.asarray(v, dtype=np.float64) / np.linalg.norm(v) for v in vertices]
    for _ in range(subdivisions):
        midpoint_cache: dict[tuple[int, int], int] = {}

        def midpoint(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in midpoint_cache:
                middle = points[a] + points[b]
                points.append(middle / np.linalg.norm(middle))
                midpoint_cache[key] = len(points) - 1
            return midpoint_cache[key]

        refined = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            refined += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = refined
    return np.asarray(points), np.asarray(faces, dtype=np.int64)


def _rock_shapes(shape_seeds: np.ndarray, subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit rocks [M, V, 3] (diameter 1 in x/y, height 1, base at z = 0) and shared faces [F, 3]."""
    sphere, faces = _icosphere(subdivisions)
    count = shape_seeds.size
    waves = 5
    directions = np.zeros((count, waves, 3))
    amplitudes = np.zeros((count, waves))
    frequencies = np.zeros((count, waves))
    phases = np.zeros((count, waves))
    stretch = np.ones((count, 3))
    for index, seed in enumerate(shape_seeds.astype(np.int64)):
        rng = np.random.default_rng(int(seed))
        vectors = rng.normal(size=(waves, 3))
        directions[index] = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
        amplitudes[index] = rng.uniform(0.04, 0.12, waves)
        frequencies[index] = rng.uniform(1.0, 3.0, waves)
        phases[index] = rng.uniform(0.0, 2.0 * np.pi, waves)
        stretch[index, :2] = rng.uniform(0.75, 1.0, 2)
    # Low-frequency radial bumps make lumpy, angular-looking rocks from a sphere.
    projection = np.einsum("mkc,vc->mkv", directions, sphere)
    radius = 1.0 + np.einsum("mk,mkv->mv", amplitudes, np.cos(frequencies[..., None] * projection * np.pi + phases[..., None]))
    shapes = sphere[None] * radius[..., None] * stretch[:, None, :]
    # A flattened underside, as rocks settle on their broadest face.
    shapes[..., 2] = np.maximum(shapes[..., 2], -0.55)
    low, high = shapes.min(axis=1, keepdims=True), shapes.max(axis=1, keepdims=True)
    centre = 0.5 * (low + high)
    size = high - low
    shapes[..., :2] = (shapes[..., :2] - centre[..., :2]) / size[..., :2].max(axis=-1, keepdims=True)
    shapes[..., 2] = (shapes[..., 2] - low[..., 2]) / size[..., 2]
    return shapes, faces


def rock_mesh(shape_seed: int, subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """One unit rock: vertices [V, 3] (widest horizontal extent 1, height 1, base at z = 0), faces [F, 3].

    The shape depends only on ``shape_seed`` (column 6 of ``Terrain.rocks``); scale it by
    (diameter, diameter, height), rotate by yaw about +z and move its base to
    (x, y, z_base) to place it, as :func:`rocks_mesh` does.
    """
    shapes, faces = _rock_shapes(np.asarray([shape_seed]), subdivisions)
    return shapes[0], faces


def rocks_mesh(rocks: np.ndarray, subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """All rocks of a rock table [M, 7] as one mesh: vertices [M * V, 3], faces [M * F, 3]."""
    rocks = np.asarray(rocks, dtype=np.float64).reshape(-1, 7)
    if rocks.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    shapes, faces = _rock_shapes(rocks[:, 6], subdivisions)
    x, y, z_base, diameter, height, yaw = (rocks[:, k] for k in range(6))
    scaled = shapes * np.stack([diameter, diameter, height], axis=1)[:, None, :]
    cos, sin = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    placed = np.empty_like(scaled)
    placed[..., 0] = cos * scaled[..., 0] - sin * scaled[..., 1] + x[:, None]
    placed[..., 1] = sin * scaled[..., 0] + cos * scaled[..., 1] + y[:, None]
    placed[..., 2] = scaled[..., 2] + z_base[:, None]
    per_rock = shapes.shape[1]
    all_faces = faces[None] + (np.arange(rocks.shape[0]) * per_rock)[:, None, None]
    return placed.reshape(-1, 3), all_faces.reshape(-1, 3)


def terrain_mesh(terrain: Terrain, *, stride: int = 1, rock_subdivisions: int = 1,
                 include_rocks: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Ground plus rocks as one mesh (vertices [N, 3], faces [F, 3]): the scene's geometry."""
    vertices, faces = heightfield_mesh(terrain, stride)
    if include_rocks and terrain.rocks.shape[0]:
        rock_vertices, rock_faces = rocks_mesh(terrain.rocks, rock_subdivisions)
        faces = np.concatenate([faces, rock_faces + vertices.shape[0]])
        vertices = np.concatenate([vertices, rock_vertices])
    return vertices, faces
