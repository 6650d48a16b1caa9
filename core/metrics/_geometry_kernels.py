"""Numba kernel for point-to-triangle distances (about 50x the numpy path's speed).

Same region classification as :func:`esgs.core.metrics.geometry.closest_points_on_triangles`,
written per pair so no [M, 3] temporaries are allocated. Importing this module raises
ImportError when numba is missing; the caller then uses numpy.
"""
from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, inline="always")
def _segment_distance2(px, py, pz, ax, ay, az, bx, by, bz):
    dx, dy, dz = bx - ax, by - ay, bz - az
    length2 = dx * dx + dy * dy + dz * dz
    t = 0.0
    if length2 > 0.0:
        t = ((px - ax) * dx + (py - ay) * dy + (pz - az) * dz) / length2
        t = min(max(t, 0.0), 1.0)
    qx, qy, qz = ax + t * dx - px, ay + t * dy - py, az + t * dz - pz
    return qx * qx + qy * qy + qz * qz


@numba.njit(cache=True)
def _triangle_distance(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    # normal length: zero for a degenerate triangle, which is handled as its edges
    nx, ny, nz = aby * acz - abz * acy, abz * acx - abx * acz, abx * acy - aby * acx
    if nx * nx + ny * ny + nz * nz <= 1e-30 * ((abx * abx + aby * aby + abz * abz) * (acx * acx + acy * acy + acz * acz) + 1e-300):
        best = _segment_distance2(px, py, pz, ax, ay, az, bx, by, bz)
        best = min(best, _segment_distance2(px, py, pz, bx, by, bz, cx, cy, cz))
        best = min(best, _segment_distance2(px, py, pz, cx, cy, cz, ax, ay, az))
        return math.sqrt(best)
    if d1 <= 0.0 and d2 <= 0.0:
        qx, qy, qz = ax, ay, az
    else:
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        cpx, cpy, cpz = px - cx, py - cy, pz - cz
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        va = d3 * d6 - d5 * d4
        vb = d5 * d2 - d1 * d6
        vc = d1 * d4 - d3 * d2
        if d3 >= 0.0 and d4 <= d3:
            qx, qy, qz = bx, by, bz
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            t = d1 / (d1 - d3)
            qx, qy, qz = ax + t * abx, ay + t * aby, az + t * abz
        elif d6 >= 0.0 and d5 <= d6:
            qx, qy, qz = cx, cy, cz
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            t = d2 / (d2 - d6)
            qx, qy, qz = ax + t * acx, ay + t * acy, az + t * acz
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
            t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            qx, qy, qz = bx + t * (cx - bx), by + t * (cy - by), bz + t * (cz - bz)
        else:
            denominator = va + vb + vc
            v, w = vb / denominator, vc / denominator
            qx, qy, qz = ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w
    qx, qy, qz = qx - px, qy - py, qz - pz
    return math.sqrt(qx * qx + qy * qy + qz * qz)


@numba.njit(cache=True, parallel=True)
def pair_distances(points, vertices, faces, point_index, face_index):
    """Distance of ``points[point_index[i]]`` to triangle ``faces[face_index[i]]``: [M]."""
    out = np.empty(len(point_index))
    for i in numba.prange(len(point_index)):
        p = point_index[i]
        f = face_index[i]
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        out[i] = _triangle_distance(points[p, 0], points[p, 1], points[p, 2],
                                    vertices[a, 0], vertices[a, 1], vertices[a, 2],
                                    vertices[b, 0], vertices[b, 1], vertices[b, 2],
                                    vertices[c, 0], vertices[c, 1], vertices[c, 2])
    return out
