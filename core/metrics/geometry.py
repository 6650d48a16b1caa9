"""Geometric accuracy of trained Gaussians against a ground-truth mesh.

The paper's geometry metric is the distance of the trained Gaussian centres to the true
surface (mean and standard deviation). This module computes it exactly (closest point on
the triangles, not on a vertex sample), both ways:

- accuracy: every Gaussian centre -> closest point of the mesh (unsigned distance);
- completeness: points sampled uniformly on the mesh surface -> nearest Gaussian centre;

and summarises them as statistics, with and without an opacity filter (nearly transparent
Gaussians barely show in renders, so both figures are reported with the threshold used),
plus precision / recall / F-score at a distance threshold. Given the training cameras,
completeness and recall count only the part of the surface they saw (:mod:`.visibility`),
and the threshold can scale with the scene (:func:`.visibility.scene_threshold`).

Everything takes and returns numpy arrays and plain dicts; no bpy. Units are the scene's
(metres for synthetic scenes).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from ..errors import ConfigError, DatasetError
from .visibility import CameraView, sample_visibility, scene_threshold

_CHUNK_PAIRS = 2_000_000  # point/triangle pairs evaluated at once (~300 MB of float64 temporaries)


# --------------------------------------------------------------------------- exact distances


def closest_points_on_triangles(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest point of triangle (a, b, c) to each point, pairwise.

    Args:
        points, a, b, c: [M, 3] one query point and one triangle per row.

    Returns:
        [M, 3] the closest points. The query's projection is classified into the Voronoi
        region of a vertex, an edge or the face of its triangle; degenerate (zero-area)
        triangles are treated as their edges.
    """
    ab, ac, ap = b - a, c - a, points - a
    bp, cp = points - b, points - c
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        on_ab = a + ab * (d1 / (d1 - d3))[:, None]
        on_ac = a + ac * (d2 / (d2 - d6))[:, None]
        on_bc = b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None]
        denominator = va + vb + vc
        inside = a + ab * (vb / denominator)[:, None] + ac * (vc / denominator)[:, None]
    # conditions in priority order: the first one that holds picks the region
    conditions = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0),
    ]
    choices = [a, b, on_ab, c, on_ac, on_bc]
    result = inside.copy()
    taken = np.zeros(len(points), dtype=bool)
    for condition, choice in zip(conditions, choices):
        pick = condition & ~taken
        result[pick] = choice[pick]
        taken |= pick
    bad = ~np.isfinite(result).all(axis=1)
    if bad.any():
        # a zero-area triangle is a segment (or a point): its closest point is on an edge
        q = points[bad]
        candidates = np.stack([_closest_on_segments(q, a[bad], b[bad]), _closest_on_segments(q, b[bad], c[bad]),
                               _closest_on_segments(q, c[bad], a[bad])], axis=1)  # [K, 3, 3]
        nearest = np.argmin(((candidates - q[:, None, :]) ** 2).sum(axis=2), axis=1)
        result[bad] = candidates[np.arange(len(nearest)), nearest]
    return result


def _closest_on_segments(points: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Closest point of each segment [start, end] to each point: all [K, 3]."""
    direction = end - start
    length2 = _dot(direction, direction)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(length2 > 0, _dot(points - start, direction) / length2, 0.0)
    return start + direction * np.clip(np.nan_to_num(t), 0.0, 1.0)[:, None]


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", u, v)


def _check_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise DatasetError(f"a mesh needs vertices [V, 3] and triangles [F, 3], got {vertices.shape} and {faces.shape}")
    if len(faces) == 0:
        raise DatasetError("the mesh has no triangles", hint="compare against a surface mesh, not a point cloud")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise DatasetError("the mesh's triangles index vertices that do not exist")
    return vertices, faces


def point_to_mesh_distances(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unsigned distance from each point to the closest point of a triangle mesh.

    Args:
        points: [N, 3] query points (Gaussian centres).
        vertices: [V, 3] mesh vertices; faces: [F, 3] vertex indices of its triangles.

    Returns:
        [N] float64 distances, exact up to rounding.

    Only the triangles that can hold the closest point are evaluated: the distance to the
    nearest vertex bounds the answer from above, and a triangle whose centroid lies
    farther than the best distance so far plus its own radius cannot be closer. Triangles
    are grouped by size so one huge triangle does not widen the search for the others.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    vertices, faces = _check_mesh(vertices, faces)
    if len(points) == 0:
        return np.zeros(0)
    corners = vertices[faces]  # [F, 3, 3]
    centroids = corners.mean(axis=1)
    radii = np.sqrt(((corners - centroids[:, None, :]) ** 2).sum(axis=2).max(axis=1))

    # The nearest vertex bounds the answer from above; each size class of triangles is
    # then searched by increasing numbers of nearest centroids until the k-th centroid is
    # so far that no unseen triangle of the class can beat the best distance so far.
    used_vertices = np.unique(faces)
    best, _ = cKDTree(vertices[used_vertices]).query(points, workers=-1)
    for members in _size_classes(radii):
        tree = cKDTree(centroids[members])
        radius = radii[members].max()
        todo = np.arange(len(points))
        for k in (16, 64):
            k = min(k, len(members))
            for start, stop in _chunks(len(todo), max(1, _CHUNK_PAIRS // k)):
                rows = todo[start:stop]
                centroid_distance, local = tree.query(points[rows], k=k, workers=-1)
                local = local.reshape(len(rows), k)
                pairs = _pair_distances(points, vertices, faces, np.repeat(rows, k), members[local.ravel()])
                best[rows] = np.minimum(best[rows], pairs.reshape(len(rows), k).min(axis=1))
                # reached: the k-th centroid is farther than best + radius, or all were seen
                if k < len(members):
                    farthest = np.asarray(centroid_distance).reshape(len(rows), k)[:, -1]
                    unresolved = farthest - radius < best[rows]
                    todo[start:stop][~unresolved] = -1
                else:
                    todo[start:stop] = -1
            todo = todo[todo >= 0]
            if len(todo) == 0 or k == len(members):
                break
        if len(todo):
            _ball_search(points, vertices, faces, members, tree, radius, todo, best)
    return best


def _pair_distances(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                    point_index: np.ndarray, face_index: np.ndarray) -> np.ndarray:
    """Distance of ``points[point_index[i]]`` to triangle ``faces[face_index[i]]``: [M]."""
    kernel = _numba_pair_distances()
    if kernel is not None:
        return kernel(points, vertices, faces, point_index, face_index)
    out = np.empty(len(point_index))
    for s, e in _chunks(len(point_index), _CHUNK_PAIRS):
        tri = faces[face_index[s:e]]
        query = points[point_index[s:e]]
        closest = closest_points_on_triangles(query, vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]])
        out[s:e] = np.linalg.norm(query - closest, axis=1)
    return out


_NUMBA_KERNEL: Any = None
USE_NUMBA = True  # tests switch it off to check the numpy path gives the same distances


def _numba_pair_distances():
    """The compiled pairwise kernel, or None without numba (the numpy path is then used)."""
    global _NUMBA_KERNEL
    if not USE_NUMBA:
        return None
    if _NUMBA_KERNEL is None:
        try:
            from ._geometry_kernels import pair_distances
        except Exception:  # noqa: BLE001 - no numba, or a numba that does not fit this numpy
            _NUMBA_KERNEL = False
        else:
            _NUMBA_KERNEL = pair_distances
    return _NUMBA_KERNEL or None


def _ball_search(points, vertices, faces, members, tree, radius, rows, best) -> None:
    """Exhaustive search of one size class for the few points its k-nearest pass left open."""
    for start, stop in _chunks(len(rows), 4096):
        chunk = rows[start:stop]
        neighbours = tree.query_ball_point(points[chunk], best[chunk] + radius + 1e-12, return_sorted=False)
        counts = np.fromiter((len(n) for n in neighbours), dtype=np.int64, count=len(neighbours))
        if counts.sum() == 0:
            continue
        local = np.concatenate([np.asarray(n, dtype=np.int64) for n in neighbours])
        distances = _pair_distances(points, vertices, faces, np.repeat(chunk, counts), members[local])
        has = counts > 0
        offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])[has]
        best[chunk[has]] = np.minimum(best[chunk[has]], np.minimum.reduceat(distances, offsets))


def _size_classes(radii: np.ndarray) -> list[np.ndarray]:
    """Triangle indices grouped so radii within a group differ by at most a factor 4."""
    positive = radii[radii > 0]
    smallest = positive.min() if len(positive) else 1.0
    level = np.floor(np.log(np.maximum(radii, smallest) / smallest) / np.log(4.0)).astype(np.int64)
    return [np.flatnonzero(level == value) for value in np.unique(level)]


def _chunks(count: int, size: int):
    for start in range(0, count, size):
        yield start, min(start + size, count)


def sample_mesh_surface(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """``count`` points uniformly distributed over the mesh's area: [count, 3]."""
    vertices, faces = _check_mesh(vertices, faces)
    corners = vertices[faces]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    if areas.sum() <= 0:
        raise DatasetError("the mesh has zero area")
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(faces), size=count, p=areas / areas.sum())
    u, v = rng.random(count), rng.random(count)
    # reflecting points outside the triangle keeps the density uniform
    outside = u + v > 1.0
    u[outside], v[outside] = 1.0 - u[outside], 1.0 - v[outside]
    a, b, c = corners[chosen, 0], corners[chosen, 1], corners[chosen, 2]
    return a + (b - a) * u[:, None] + (c - a) * v[:, None]


def nearest_point_distances(queries: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance from each query [M, 3] to its nearest point in ``points`` [N, 3]: [M]."""
    from scipy.spatial import cKDTree

    if len(points) == 0:
        return np.full(len(queries), np.inf)
    distances, _ = cKDTree(np.asarray(points, dtype=np.float64)).query(np.asarray(queries, dtype=np.float64))
    return distances


# --------------------------------------------------------------------------- statistics


def distance_statistics(distances: np.ndarray) -> dict[str, Any]:
    """count, mean, std, median, p95, rms and max of ``distances`` [N] (None when empty)."""
    distances = np.asarray(distances, dtype=np.float64)
    if len(distances) == 0:
        return {"count": 0, "mean": None, "std": None, "median": None, "p95": None, "rms": None, "max": None}
    return {
        "count": int(len(distances)),
        "mean": float(distances.mean()),
        "std": float(distances.std()),
        "median": float(np.median(distances)),
        "p95": float(np.percentile(distances, 95)),
        "rms": float(np.sqrt(np.mean(distances**2))),
        "max": float(distances.max()),
    }


@dataclasses.dataclass
class MeshComparison:
    """Result of :func:`compare_points_to_mesh`.

    ``distances`` [N] is the distance of every Gaussian centre (filtered or not) to the
    mesh, for colouring; ``summary`` is the JSON-ready report.
    """

    distances: np.ndarray
    kept: np.ndarray
    summary: dict[str, Any]


def compare_points_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, *,
                           opacities: Optional[np.ndarray] = None, opacity_min: float = 0.5,
                           threshold_m: Optional[float] = 0.05, n_surface_samples: int = 100_000,
                           seed: int = 0, cameras: Optional[Sequence[CameraView]] = None) -> MeshComparison:
    """Compare Gaussian centres with a ground-truth mesh.

    Args:
        points: [N, 3] Gaussian centres, in the mesh's frame and units.
        vertices: [V, 3] and faces: [F, 3]: the ground-truth triangle mesh.
        opacities: [N] activated opacities in [0, 1]; None treats every Gaussian as opaque.
        opacity_min: Gaussians below this opacity are left out of the filtered figures.
        threshold_m: distance under which a centre (precision) or a surface sample
            (recall) counts as matched; None: scaled to the scene by
            :func:`~.visibility.scene_threshold` (1 % of the median camera-to-surface
            distance with cameras, 0.5 % of the mesh's bounding-box diagonal without).
        n_surface_samples: surface samples for completeness and recall.
        seed: seed of the surface sampling, recorded in the summary.
        cameras: the training cameras (:class:`~.visibility.CameraView`, same frame). When
            given, completeness and recall count only the surface samples they saw
            (:func:`~.visibility.visible_surface_samples`): a reconstruction cannot cover
            what no image shows. None: the whole mesh counts.

    Returns:
        A :class:`MeshComparison`; ``summary`` holds ``gaussians_to_mesh`` (all
        centres), ``gaussians_to_mesh_filtered``, ``mesh_to_gaussians`` (surface samples
        to filtered centres), ``precision``, ``recall``, ``fscore``, ``threshold_m`` and
        ``threshold_rule``, and the settings used. With cameras also ``recall_scope``
        ("visible"), ``n_cameras``, ``n_visible_samples``, ``visible_fraction`` and
        ``recall_whole_mesh`` (recall over every sample, for reference). Precision, recall,
        F-score and ``recall_whole_mesh`` are None when no centre passes ``opacity_min``.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if threshold_m is not None and threshold_m <= 0:
        raise ConfigError(f"the distance threshold must be positive, got {threshold_m}")
    if n_surface_samples <= 0:
        raise ConfigError(f"the number of surface samples must be positive, got {n_surface_samples}")
    if opacities is None:
        kept = np.ones(len(points), dtype=bool)
    else:
        opacities = np.asarray(opacities, dtype=np.float64).reshape(-1)
        if len(opacities) != len(points):
            raise ConfigError(f"{len(opacities)} opacities for {len(points)} points")
        kept = opacities >= opacity_min
    distances = point_to_mesh_distances(points, vertices, faces)
    samples = sample_mesh_surface(vertices, faces, n_surface_samples, seed=seed)
    completeness = nearest_point_distances(samples, points[kept])
    visible = np.ones(len(samples), dtype=bool)
    viewing_distance = None
    if cameras is not None:
        vertices_array, faces_array = _check_mesh(vertices, faces)
        visible, viewing_distance = sample_visibility(vertices_array, faces_array, samples, list(cameras))
    if threshold_m is None:
        threshold_m, rule = scene_threshold(viewing_distance, np.asarray(vertices, dtype=np.float64))
    else:
        rule = "given"
    filtered = distances[kept]
    seen_completeness = completeness[visible]
    if len(filtered):
        precision = float(np.mean(filtered <= threshold_m))
        recall = float(np.mean(seen_completeness <= threshold_m)) if len(seen_completeness) else 0.0
        fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    else:
        # no centre passes the opacity filter: the scores are undefined, not zero (a run
        # whose Gaussians are all faint is not "a bad match"; lowering the filter tells)
        precision = recall = fscore = None
    summary = {
        "units": "scene units (metres for synthetic scenes)",
        "n_gaussians": int(len(points)),
        "opacity_min": float(opacity_min) if opacities is not None else None,
        "n_gaussians_filtered": int(kept.sum()),
        "threshold_m": float(threshold_m),
        "threshold_rule": rule,
        "n_surface_samples": int(n_surface_samples),
        "seed": int(seed),
        "recall_scope": "whole mesh" if cameras is None else "surface seen by the training cameras",
        "gaussians_to_mesh": distance_statistics(distances),
        "gaussians_to_mesh_filtered": distance_statistics(filtered),
        "mesh_to_gaussians": distance_statistics(seen_completeness if len(filtered) else np.zeros(0)),
        "precision": precision,
        "recall": recall,
        "fscore": None if fscore is None else float(fscore),
    }
    if cameras is not None:
        summary.update({
            "n_cameras": len(list(cameras)),
            "n_visible_samples": int(visible.sum()),
            "visible_fraction": float(visible.mean()),
            "recall_whole_mesh": float(np.mean(completeness <= threshold_m)) if len(filtered) else None,
        })
    return MeshComparison(distances=distances, kept=kept, summary=summary)


def load_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [V, 3] and triangles [F, 3] of a mesh file (PLY, OBJ, GLB...; scenes merged).

    Raises:
        DatasetError: the file is missing, unreadable or holds no triangles.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise DatasetError("mesh file not found", path=path)
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # noqa: BLE001 - trimesh raises many types for bad files
        raise DatasetError(f"cannot read the mesh: {err}", path=path) from err
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
    if len(faces) == 0:
        raise DatasetError("the file holds no triangles", path=path, hint="give a surface mesh")
    return np.asarray(mesh.vertices, dtype=np.float64), faces.astype(np.int64)


def compare_ply_to_mesh(gaussians_path: str | Path, mesh_path: str | Path, **options) -> MeshComparison:
    """:func:`compare_points_to_mesh` for a 3DGS PLY file against a mesh file.

    ``options`` are those of :func:`compare_points_to_mesh` (opacity_min, threshold_m, ...);
    the opacities come from the PLY (activated).
    """
    from ..formats.ply import read_gaussians_ply

    gaussians = read_gaussians_ply(gaussians_path)
    vertices, faces = load_mesh(mesh_path)
    return compare_points_to_mesh(np.asarray(gaussians.means, dtype=np.float64), vertices, faces,
                                  opacities=gaussians.opacities(), **options)
