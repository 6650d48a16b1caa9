"""COLMAP camera models: parameter counts, names and the pinhole part of each.

The table mirrors ``pycolmap.CameraModelId`` (pycolmap 4.2) so that validation and
``pinhole_part`` work without building pycolmap objects; a test checks it against
pycolmap's own ``params_info``, ``focal_length_idxs`` and ``principal_point_idxs``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DatasetError


@dataclass(frozen=True)
class CameraModelInfo:
    """What the project needs to know about one COLMAP camera model."""

    model_id: int
    name: str
    param_names: tuple[str, ...]
    focal_idxs: tuple[int, ...]  # one index (shared f) or two (fx, fy); empty = no pinhole part
    principal_point_idxs: tuple[int, ...]  # (cx, cy) indices; empty = no pinhole part

    @property
    def num_params(self) -> int:
        return len(self.param_names)

    @property
    def has_pinhole_part(self) -> bool:
        return bool(self.focal_idxs) and bool(self.principal_point_idxs)


def _info(model_id: int, name: str, params: str) -> CameraModelInfo:
    names = tuple(part.strip() for part in params.split(","))
    if names[0] == "f":
        focal, principal = (0,), (1, 2)
    elif names[0] == "fx":
        focal, principal = (0, 1), (2, 3)
    else:  # spherical models (EQUIRECTANGULAR) have no focal length
        focal, principal = (), ()
    return CameraModelInfo(model_id, name, names, focal, principal)


CAMERA_MODELS: dict[str, CameraModelInfo] = {
    info.name: info
    for info in (
        _info(0, "SIMPLE_PINHOLE", "f, cx, cy"),
        _info(1, "PINHOLE", "fx, fy, cx, cy"),
        _info(2, "SIMPLE_RADIAL", "f, cx, cy, k"),
        _info(3, "RADIAL", "f, cx, cy, k1, k2"),
        _info(4, "OPENCV", "fx, fy, cx, cy, k1, k2, p1, p2"),
        _info(5, "OPENCV_FISHEYE", "fx, fy, cx, cy, k1, k2, k3, k4"),
        _info(6, "FULL_OPENCV", "fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6"),
        _info(7, "FOV", "fx, fy, cx, cy, omega"),
        _info(8, "SIMPLE_RADIAL_FISHEYE", "f, cx, cy, k"),
        _info(9, "RADIAL_FISHEYE", "f, cx, cy, k1, k2"),
        _info(10, "THIN_PRISM_FISHEYE", "fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1"),
        _info(
            11,
            "RAD_TAN_THIN_PRISM_FISHEYE",
            "fx, fy, cx, cy, k0, k1, k2, k3, k4, k5, p0, p1, s0, s1, s2, s3",
        ),
        _info(12, "SIMPLE_DIVISION", "f, cx, cy, k"),
        _info(13, "DIVISION", "fx, fy, cx, cy, k"),
        _info(14, "SIMPLE_FISHEYE", "f, cx, cy"),
        _info(15, "FISHEYE", "fx, fy, cx, cy"),
        _info(16, "EUCM", "fx, fy, cx, cy, alpha, beta"),
        _info(17, "EQUIRECTANGULAR", "w, h"),
    )
}
CAMERA_MODELS_BY_ID: dict[int, CameraModelInfo] = {info.model_id: info for info in CAMERA_MODELS.values()}

#: Models whose projection is the plain pinhole one (no distortion, no fisheye mapping).
PINHOLE_MODELS = frozenset({"SIMPLE_PINHOLE", "PINHOLE"})


def model_info(model: str | int) -> CameraModelInfo:
    """The table entry for a model name ("OPENCV") or numeric id (4); DatasetError if unknown."""
    info = CAMERA_MODELS_BY_ID.get(model) if isinstance(model, (int, np.integer)) else CAMERA_MODELS.get(str(model))
    if info is None:
        known = ", ".join(CAMERA_MODELS)
        raise DatasetError(f"unknown COLMAP camera model {model!r}", hint=f"known models: {known}")
    return info


def pinhole_part(model: str, params: np.ndarray) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a camera model's pinhole part, whatever its distortion terms.

    ``params``: [P] in COLMAP's order for ``model``. Models with one focal length give
    fx == fy. Spherical models (EQUIRECTANGULAR) have no pinhole part: DatasetError.
    """
    info = model_info(model)
    values = np.asarray(params, dtype=np.float64).reshape(-1)
    if values.shape[0] != info.num_params:
        raise DatasetError(
            f"camera model {info.name} takes {info.num_params} parameters ({', '.join(info.param_names)}), "
            f"got {values.shape[0]}"
        )
    if not info.has_pinhole_part:
        raise DatasetError(
            f"camera model {info.name} is spherical and has no pinhole intrinsics",
            hint="convert the images to perspective views first",
        )
    fx = float(values[info.focal_idxs[0]])
    fy = float(values[info.focal_idxs[-1]])
    cx = float(values[info.principal_point_idxs[0]])
    cy = float(values[info.principal_point_idxs[1]])
    return fx, fy, cx, cy
