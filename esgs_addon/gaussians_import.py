"""Import trained Gaussians (a 3DGS PLY) as one point-cloud object.

Public entry point: :func:`import_gaussians`. The object holds every Gaussian with its
activated parameters as point attributes:

==============  ============  ===========================================================
attribute       type          value
==============  ============  ===========================================================
``position``    vector        centre (the PLY's x y z, in the object's local frame)
``scale``       vector        activated axis scales ``exp(scale_i)``
``rotation``    quaternion    unit rotation (w, x, y, z), the PLY's ``rot_*`` normalised
``opacity``     float         activated opacity ``sigmoid(opacity)``
``color``       colour        ``clamp(0.5 + C0 * f_dc, 0, 1)`` as scene-linear RGB (the
                              3DGS value is display sRGB; Blender colours are linear)
``sh_dc``       vector        raw ``f_dc_*`` (only with ``keep_sh``)
``sh_rest_k``   vector        raw higher-order coefficient k (RGB), with ``keep_sh``
==============  ============  ===========================================================

A geometry-node modifier (:mod:`.gaussian_nodes`) shows them as points or ellipsoids,
filtered by opacity and capped in number; those are modifier inputs, so they can be
changed later. Attributes are written with ``foreach_set``: no per-Gaussian Python loop.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import bpy
import numpy as np

from ..core.errors import ConfigError
from ..core.formats.ply import GaussianPly, read_gaussians_ply
from . import gaussian_nodes, pointcloud

#: degree-0 spherical-harmonic basis constant, 1 / (2 sqrt(pi))
SH_C0 = 0.28209479177387814
MODES = ("points", "ellipsoids")
PROP_SOURCE = "esgs_gaussians_source"
PROP_COUNT = "esgs_gaussian_count"
PROP_SH_DEGREE = "esgs_sh_degree"


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """The sRGB transfer function inverted (IEC 61966-2-1), element-wise on [0, 1] values."""
    values = np.asarray(values, dtype=np.float32)
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4).astype(np.float32)


def gaussian_colours(sh_dc: np.ndarray) -> np.ndarray:
    """Display colour of each Gaussian from its degree-0 SH coefficient: [N, 3] -> [N, 3] in [0, 1]."""
    return np.clip(0.5 + SH_C0 * np.asarray(sh_dc, dtype=np.float32), 0.0, 1.0)


def gaussian_attributes(gaussians: GaussianPly, keep_sh: bool = False) -> dict[str, np.ndarray]:
    """The point attributes of :func:`import_gaussians` as numpy arrays (without rotation).

    Returns name -> array: ``scale`` [N, 3], ``opacity`` [N], ``color`` [N, 4] (linear RGBA,
    alpha 1) and, with ``keep_sh``, ``sh_dc`` [N, 3] and ``sh_rest_<k>`` [N, 3].
    """
    n = len(gaussians)
    colour = np.ones((n, 4), dtype=np.float32)
    colour[:, :3] = srgb_to_linear(gaussian_colours(gaussians.sh_dc))
    attributes = {"scale": gaussians.scales(), "opacity": gaussians.opacities(), "color": colour}
    if keep_sh:
        attributes["sh_dc"] = gaussians.sh_dc
        for k in range(gaussians.sh_rest.shape[1]):
            attributes[f"sh_rest_{k}"] = np.ascontiguousarray(gaussians.sh_rest[:, k, :])
    return attributes


def import_gaussians(filepath: str | Path, name: Optional[str] = None, opacity_min: float = 0.0,
                     max_display: int = 1_000_000, mode: str = "points", *, keep_sh: bool = False,
                     point_radius: Optional[float] = None, collection: Optional[bpy.types.Collection] = None,
                     matrix_world: Optional[np.ndarray] = None) -> bpy.types.Object:
    """Create a point-cloud object from a 3DGS PLY; returns the object.

    Args:
        filepath: the PLY (``RUN/point_cloud.ply``).
        name: object name (default: the file's parent folder name, e.g. the run's).
        opacity_min: display filter: Gaussians below this opacity are hidden (kept in the data).
        max_display: display cap: about this many Gaussians are shown (a random subset).
        mode: ``"points"`` or ``"ellipsoids"``.
        keep_sh: also store the raw SH coefficients (for export or view-dependent colour).
        point_radius: radius of the points in scene units (default: median Gaussian scale).
        collection: where to link the object (default: the context's collection).
        matrix_world: [4, 4] placement (e.g. a COLMAP scene's "Blender from COLMAP" transform).

    Raises:
        FormatError: not a 3DGS PLY, or truncated; nothing is created.
        ConfigError: a bad option; nothing is created.
    """
    if mode not in MODES:
        raise ConfigError(f"unknown display mode {mode!r}", hint=f"use one of {', '.join(MODES)}")
    if not 0.0 <= opacity_min <= 1.0:
        raise ConfigError(f"opacity_min must be within [0, 1], got {opacity_min}")
    if max_display < 0:
        raise ConfigError(f"max_display must not be negative, got {max_display}")
    filepath = Path(filepath).expanduser()
    gaussians = read_gaussians_ply(filepath)  # FormatError before anything exists in Blender
    attributes = gaussian_attributes(gaussians, keep_sh=keep_sh)
    if point_radius is None:
        point_radius = float(np.median(attributes["scale"].mean(axis=1))) if len(gaussians) else 0.01
    if name is None:
        name = filepath.parent.name if filepath.stem == "point_cloud" and filepath.parent.name else filepath.stem
    if collection is None:
        collection = bpy.context.collection or bpy.context.scene.collection

    obj = pointcloud.point_cloud_object(name, gaussians.means, attributes, radius=point_radius,
                                        collection=collection)
    try:
        rotation = obj.data.attributes.new("rotation", "QUATERNION", "POINT")
        rotation.data.foreach_set("value", gaussians.rotations_normalised().reshape(-1))
        obj[PROP_SOURCE] = str(filepath)
        obj[PROP_COUNT] = len(gaussians)
        obj[PROP_SH_DEGREE] = gaussians.sh_degree
        if matrix_world is not None:
            from mathutils import Matrix

            obj.matrix_world = Matrix(np.asarray(matrix_world, dtype=np.float64).reshape(4, 4).tolist())
        gaussian_nodes.add_gaussian_modifier(
            obj, ellipsoids=(mode == "ellipsoids"), opacity_min=float(opacity_min),
            max_display=int(min(max_display, 2**31 - 1)), point_radius=float(point_radius),
        )
    except BaseException:
        remove_object(obj)
        raise
    return obj


def remove_object(obj: bpy.types.Object) -> None:
    """Delete an object and its point-cloud data (used to undo a half-built import)."""
    data = obj.data
    bpy.data.objects.remove(obj)
    if isinstance(data, bpy.types.PointCloud) and data.users == 0:
        bpy.data.pointclouds.remove(data)


def is_gaussian_object(obj: Optional[bpy.types.Object]) -> bool:
    """Whether ``obj`` is a point cloud made by :func:`import_gaussians`."""
    return obj is not None and obj.type == "POINTCLOUD" and PROP_COUNT in obj


def read_gaussian_arrays(obj: bpy.types.Object) -> dict[str, np.ndarray]:
    """Centres [N, 3] (local frame), ``opacity`` [N] and ``rotation`` [N, 4] of a Gaussian object."""
    attributes = obj.data.attributes
    count = len(obj.data.points)
    positions = np.zeros(count * 3, dtype=np.float32)
    attributes["position"].data.foreach_get("vector", positions)
    out = {"position": positions.reshape(count, 3)}
    if "opacity" in attributes:
        out["opacity"] = pointcloud.read_point_attribute(obj, "opacity")
    if "rotation" in attributes:
        rotation = np.zeros(count * 4, dtype=np.float32)
        attributes["rotation"].data.foreach_get("value", rotation)
        out["rotation"] = rotation.reshape(count, 4)
    return out
