"""Prior maps on disk: ``SCENE/priors/<source>/{depth,normal,mask}/<stem>.{exr,png}``.

One format for every source (``gt`` synthetic ground truth, ``labels`` rendered from a mesh,
``ndn`` the diffusion prior, ``sfm`` projected COLMAP points):

- depth EXR, channel ``Z``: distance along the camera z axis in scene units (metres for
  synthetic scenes, SfM units for reconstructions); 0 = no value. Header ``depth_kind`` is
  ``metric`` or ``relative`` (known up to scale and shift; aligned during training).
- normal EXR, channels ``X, Y, Z``: unit normals; header ``frame`` is ``camera_opencv``
  (x right, y down, z forward; what we write) or ``world`` (converted on load with the pose).
- mask PNG: 255 = valid surface, 0 = sky / no surface / no prior. Header ``mask_kind`` of the
  depth and normal EXRs says what 0 means: ``surface`` (the source knows where there is no
  surface at all: 0 is sky; gt and ndn) or ``coverage`` (0 only means "no value here": sparse
  SfM points, stereo holes). Files without the header follow their source (:attr:`PriorSource.mask_kind`).

Optional kinds (the fused ``auto`` source writes the first two, ``ndn`` the last two):

- confidence EXR, channel ``Z``: per-pixel trust in [0, 1] that scales the prior losses
  (missing: 1 wherever the mask is valid);
- sky PNG: 255 = no surface along the ray. It wins over a ``surface`` mask's zeros, so a
  source whose mask only means coverage can still say where the sky is;
- second depth EXR (``second_depth/<stem>.exr``), channel ``Z``: a second, independent
  estimate of the same depth with its own ``depth_kind`` (``ndn``: its normals network's own
  depth, which ``auto`` blends with the first in the holes of views with sky).

``<stem>`` is the image name without its extension (sub-folders kept).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..formats.imageio import read_depth_exr, read_image, read_normal_exr, write_depth_exr, write_normal_exr, write_png
from ..formats.scene_dir import PriorSource, SceneDir

CAMERA_FRAME = "camera_opencv"
MASK_KINDS = ("surface", "coverage")


@dataclass
class PriorMaps:
    """The priors of one view at one resolution. ``None`` where the source has no such map."""

    depth: np.ndarray | None  # [H, W] float32, 0 = invalid
    normal: np.ndarray | None  # [H, W, 3] float32, camera frame (OpenCV axes)
    mask: np.ndarray  # [H, W] bool, True = valid surface
    relative_depth: bool = False
    source: str = ""
    sky: np.ndarray | None = None  # [H, W] bool, True = no surface along the ray; None = unknown
    confidence: np.ndarray | None = None  # [H, W] float32 in [0, 1]; None = full trust where valid
    # a second, independent depth estimate of the same view (0 = invalid; ``ndn``: its normals
    # network's own depth), and whether it is relative; None = the source has none
    second_depth: np.ndarray | None = None
    second_relative_depth: bool = False

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape  # type: ignore[return-value]


def prior_dir(scene_dir: str | Path, source: str) -> Path:
    """``SCENE/priors/<source>``."""
    return SceneDir(scene_dir).prior(source)


def _fallback_mask_kind(source: str) -> str:
    """What a mask's zeros mean in files written before the ``mask_kind`` header: the source's
    kind (:attr:`PriorSource.mask_kind`); "coverage" for a source we do not know."""
    try:
        return PriorSource(source).mask_kind
    except ValueError:
        return "coverage"


def available_prior_sources(scene_dir: str | Path) -> list[str]:
    """Sources present under ``SCENE/priors`` (folders with a depth or normal sub-folder)."""
    root = SceneDir(scene_dir).priors
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if (p / "depth").is_dir() or (p / "normal").is_dir())


def write_prior_maps(scene_dir: str | Path, source: str, image_name: str, *, depth: np.ndarray | None = None,
                     normal: np.ndarray | None = None, mask: np.ndarray | None = None, relative_depth: bool = False,
                     units: str = "m", metadata: dict[str, str] | None = None,
                     mask_kind: str = "coverage", confidence: np.ndarray | None = None,
                     sky: np.ndarray | None = None, second_depth: np.ndarray | None = None,
                     second_relative_depth: bool = False) -> None:
    """Write one view's prior maps atomically in the standard layout.

    ``mask_kind`` "surface" when the mask's zeros are pixels with no surface at all (sky), so
    training may push them far away; "coverage" when they only lack a value. ``confidence``
    [H, W] in [0, 1], ``sky`` [H, W] bool and ``second_depth`` [H, W] (a second estimate of the
    view's depth, relative when ``second_relative_depth``) are the optional kinds (module docstring).
    """
    if mask_kind not in MASK_KINDS:
        raise ValueError(f"mask_kind must be one of {MASK_KINDS}, got {mask_kind!r}")
    scene = SceneDir(scene_dir)
    extra = {"source": str(source), "mask_kind": mask_kind, **(metadata or {})}
    if depth is not None:
        write_depth_exr(scene.depth_map(source, image_name), np.asarray(depth, np.float32), units=units,
                        metadata={**extra, "depth_kind": "relative" if relative_depth else "metric"})
    if normal is not None:
        write_normal_exr(scene.normal_map(source, image_name), np.asarray(normal, np.float32), frame=CAMERA_FRAME,
                         metadata=extra)
    if mask is not None:
        write_png(scene.mask_map(source, image_name), np.where(np.asarray(mask, bool), 255, 0).astype(np.uint8))
    if confidence is not None:
        values = np.clip(np.nan_to_num(np.asarray(confidence, np.float32)), 0.0, 1.0)
        write_depth_exr(scene.confidence_map(source, image_name), values, units="1",
                        metadata={**extra, "kind": "confidence"})
    if sky is not None:
        write_png(scene.sky_map(source, image_name), np.where(np.asarray(sky, bool), 255, 0).astype(np.uint8))
    if second_depth is not None:
        second_units = "relative" if second_relative_depth else ("m" if units == "relative" else units)
        write_depth_exr(scene.second_depth_map(source, image_name), np.asarray(second_depth, np.float32),
                        units=second_units,
                        metadata={**extra, "depth_kind": "relative" if second_relative_depth else "metric",
                                  "kind": "second_depth"})


def _resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize a depth map without blending across edges: block-minimum of valid values for an
    integer shrink (keeps sparse SfM samples), nearest neighbour otherwise."""
    import cv2

    in_height, in_width = depth.shape
    if (in_height, in_width) == (height, width):
        return depth
    fy, fx = in_height / height, in_width / width
    if fx == fy and float(fx).is_integer() and fx > 1:
        factor = int(fx)
        blocks = np.where(depth > 0, depth, np.inf).reshape(height, factor, width, factor)
        reduced = blocks.min(axis=(1, 3))
        return np.where(np.isfinite(reduced), reduced, 0.0).astype(np.float32)
    return cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)


def _resize_nearest(array: np.ndarray, width: int, height: int) -> np.ndarray:
    import cv2

    if array.shape[:2] == (height, width):
        return array
    return cv2.resize(array, (width, height), interpolation=cv2.INTER_NEAREST)


def load_prior_maps(scene_dir: str | Path, source: str, image_name: str, *, size: tuple[int, int] | None = None,
                    world_to_camera_rotation: np.ndarray | None = None) -> PriorMaps:
    """Read one view's priors, checked and brought to ``size`` = (width, height) if given.

    Depth and mask must share a size; normals stored in the ``world`` frame are rotated into
    the camera frame with ``world_to_camera_rotation`` [3,3] (required then). Raises
    :class:`DatasetError` naming the file for a missing view, mismatched sizes or an unknown
    frame.
    """
    scene = SceneDir(scene_dir)
    root = scene.prior(source)
    depth_path, normal_path, mask_path = (scene.depth_map(source, image_name), scene.normal_map(source, image_name),
                                          scene.mask_map(source, image_name))
    if not root.is_dir():
        raise DatasetError(f"no prior folder for source {source!r}", path=root,
                           hint=f"available: {', '.join(available_prior_sources(scene_dir)) or 'none'}; "
                                f"make one with `esgs priors SCENE --method {source}`")
    depth = normal = None
    relative = False
    mask_kind = ""
    if depth_path.exists():
        depth, header, relative = _read_depth_map(depth_path)
        mask_kind = header.get("mask_kind", "")
    if normal_path.exists():
        normal, header = read_normal_exr(normal_path)
        mask_kind = mask_kind or header.get("mask_kind", "")
        frame = header.get("frame", CAMERA_FRAME)
        if frame == "world":
            if world_to_camera_rotation is None:
                raise DatasetError("normals are in the world frame but no camera pose was given", path=normal_path)
            normal = normal @ np.asarray(world_to_camera_rotation, np.float32).T
        elif frame != CAMERA_FRAME:
            raise DatasetError(f"unknown normal frame {frame!r} (expected {CAMERA_FRAME} or world)", path=normal_path)
        normal = np.nan_to_num(normal.astype(np.float32))
    if depth is None and normal is None and not mask_path.exists():
        raise DatasetError(f"no depth, normal or mask prior for image {image_name!r}", path=root,
                           hint=f"expected {depth_path.name} under depth/ or normal/, or {mask_path.name} under mask/")
    if depth is None and normal is None:
        # masks alone (a folder of sky masks): their size is the maps' size
        mask_image = read_image(mask_path)
        height, width = mask_image.shape[:2]
    else:
        reference = depth if depth is not None else normal
        height, width = reference.shape[:2]
    if depth is not None and normal is not None and normal.shape[:2] != depth.shape:
        raise DatasetError(f"normal map {normal.shape[1]}x{normal.shape[0]} does not match depth map "
                           f"{width}x{height}", path=normal_path)
    if mask_path.exists():
        mask_image = read_image(mask_path)
        mask = (mask_image if mask_image.ndim == 2 else mask_image[..., 0]) > 127
        if mask.shape != (height, width):
            raise DatasetError(f"mask {mask.shape[1]}x{mask.shape[0]} does not match the prior maps {width}x{height}",
                               path=mask_path)
    else:
        mask = np.ones((height, width), bool)
    if depth is not None:
        mask = mask & (depth > 0) if source == PriorSource.SFM else mask
    if size is not None:
        target_width, target_height = size
        if abs(target_width / width - target_height / height) > 0.02:
            raise DatasetError(f"prior maps are {width}x{height} but the view is {target_width}x{target_height} "
                               f"(different aspect ratio)", path=root)
        if depth is not None:
            depth = _resize_depth(depth, target_width, target_height)
        if normal is not None:
            normal = _resize_nearest(normal, target_width, target_height)
        if depth is not None and source == PriorSource.SFM:
            mask = depth > 0  # sparse samples: nearest resizing of the mask would drop them
        else:
            mask = _resize_nearest(mask.astype(np.uint8), target_width, target_height).astype(bool)
    if normal is not None:
        length = np.linalg.norm(normal, axis=-1, keepdims=True)
        normal = np.where(length > 1e-6, normal / np.maximum(length, 1e-6), 0.0).astype(np.float32)
    mask_kind = mask_kind or _fallback_mask_kind(source)
    if mask_kind not in MASK_KINDS:
        raise DatasetError(f"unknown mask_kind {mask_kind!r} (expected {' or '.join(MASK_KINDS)})",
                           path=depth_path if depth is not None else normal_path)
    sky = ~mask if mask_kind == "surface" and mask_path.exists() else None
    out_size = (mask.shape[1], mask.shape[0])
    sky_path = scene.sky_map(source, image_name)
    if sky_path.exists():
        sky = _read_plane(sky_path, (width, height), out_size, kind="sky") > 127
    confidence = None
    confidence_path = scene.confidence_map(source, image_name)
    if confidence_path.exists():
        confidence = np.clip(_read_plane(confidence_path, (width, height), out_size, kind="confidence"), 0.0, 1.0)
    second_depth, second_relative = _read_second_depth(scene.second_depth_map(source, image_name), (width, height),
                                                       out_size)
    return PriorMaps(depth=depth, normal=normal, mask=mask, relative_depth=relative, source=source, sky=sky,
                     confidence=confidence, second_depth=second_depth, second_relative_depth=second_relative)


def _read_second_depth(path: Path, stored: tuple[int, int],
                       size: tuple[int, int]) -> tuple[np.ndarray | None, bool]:
    """The optional second depth map (None when absent) at ``size``, resized as depth is, and
    whether it is relative; checked against the stored prior maps' size (width, height)."""
    if not path.exists():
        return None, False
    depth, _, relative = _read_depth_map(path)
    if (depth.shape[1], depth.shape[0]) != stored:
        raise DatasetError(f"second depth map {depth.shape[1]}x{depth.shape[0]} does not match the prior maps "
                           f"{stored[0]}x{stored[1]}", path=path, hint="recompute the priors (esgs priors SCENE --method ndn)")
    return _resize_depth(depth, *size), relative


def _read_depth_map(path: Path) -> tuple[np.ndarray, dict[str, str], bool]:
    """A depth EXR as (float32 depth with non-finite values as 0, its header, whether its
    ``depth_kind`` is relative); :class:`DatasetError` for an unknown kind."""
    depth, header = read_depth_exr(path)
    kind = header.get("depth_kind", "metric")
    if kind not in ("metric", "relative"):
        raise DatasetError(f"unknown depth_kind {kind!r} (expected metric or relative)", path=path)
    return np.nan_to_num(depth.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0), header, kind == "relative"


def _read_plane(path: Path, stored: tuple[int, int], size: tuple[int, int], *, kind: str) -> np.ndarray:
    """One optional single-channel map (sky PNG, confidence EXR) checked against the stored
    prior maps' size (width, height) and brought to ``size`` by nearest sampling."""
    if path.suffix == ".exr":
        plane, _ = read_depth_exr(path)
        plane = np.nan_to_num(plane.astype(np.float32))
    else:
        image = read_image(path)
        plane = image if image.ndim == 2 else image[..., 0]
    if (plane.shape[1], plane.shape[0]) != stored:
        raise DatasetError(f"{kind} map {plane.shape[1]}x{plane.shape[0]} does not match the prior maps "
                           f"{stored[0]}x{stored[1]}", path=path, hint="recompute the priors (esgs priors SCENE --method auto)")
    return _resize_nearest(plane, *size)
