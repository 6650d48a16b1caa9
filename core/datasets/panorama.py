"""Pinhole views cut from a panorama.

An equirectangular panorama (2:1, longitude across, latitude down) is resampled into true
pinhole views whose intrinsics and rotations are known exactly, so the scene folder gets a
COLMAP model of one camera station (every centre at the origin). A flat strip (any other
aspect) has no known projection, so it is only cut into overlapping crops.

World frame of the equirectangular image (OpenCV-like, y down): longitude ``lon`` is 0 at the
panorama's centre column and grows to the right; latitude ``lat`` is +pi/2 at the top row.
The direction of (lon, lat) is ``(cos(lat) sin(lon), -sin(lat), cos(lat) cos(lon))``.
A view with yaw ``yaw`` and pitch ``pitch`` (up positive) has camera-to-world rotation
``R_y(yaw) @ R_x(pitch)``.

Overlap is measured in pixels along the centre row: the fraction of a view's width that
its right-hand neighbour also sees (the "30-60 % overlap" of tiled panoramas).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..colmap.model import Camera
from ..errors import ConfigError, DatasetError
from ..progress import ProgressCallback, ProgressEvent, no_progress
from ..formats.scene_dir import SceneDir
from .common import rotation_x, rotation_y, scene_provenance, station_model


@dataclass
class PanoramaOptions:
    """How to cut a panorama into views."""

    width: int = field(default=1920, metadata={"help": "output view width in pixels"})
    height: int = field(default=1080, metadata={"help": "output view height in pixels"})
    overlap: float = field(default=0.4, metadata={"help": "minimum fraction of a view's width shared with its neighbour (0.3-0.6 typical)"})
    fov_deg: float = field(default=60.0, metadata={"help": "horizontal field of view of each view (equirectangular input), degrees"})
    pitches_deg: tuple[float, ...] = field(default=(0.0,), metadata={"help": "pitch of each row of views, degrees (up positive)"})
    equirectangular: bool | None = field(default=None, metadata={"help": "force (True) or refuse (False) equirectangular handling; default: 2:1 aspect"})
    overwrite: bool = field(default=False, metadata={"help": "replace an existing output folder"})

    def validate(self) -> None:
        if self.width < 16 or self.height < 16:
            raise ConfigError(f"view size {self.width}x{self.height} is too small", hint="use at least 16x16 pixels")
        if not 0.0 <= self.overlap < 0.95:
            raise ConfigError(f"overlap {self.overlap} must be in [0, 0.95)", hint="0.3 to 0.6 is typical")
        if not 1.0 <= self.fov_deg < 170.0:
            raise ConfigError(f"fov_deg {self.fov_deg} must be in [1, 170)")
        if not self.pitches_deg or any(abs(p) > 90.0 for p in self.pitches_deg):
            raise ConfigError(f"pitches_deg {self.pitches_deg} must be non-empty and within [-90, 90]")


def focal_from_fov(width: int, fov_deg: float) -> float:
    """Focal length in pixels of a pinhole view ``width`` pixels wide with horizontal ``fov_deg``."""
    return 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)


def yaw_step_for_overlap(fov_deg: float, overlap: float) -> float:
    """Yaw step (radians) at which two pinhole views share ``overlap`` of their centre row's pixels.

    A centre-row pixel at angle a from the axis lies at ``f tan(a)``; the neighbour (yawed by
    s) sees the pixels with ``a >= s - fov/2``, i.e. a fraction ``(1 - tan(s - fov/2)/tan(fov/2)) / 2``.
    """
    half = math.radians(fov_deg) / 2.0
    return half + math.atan(math.tan(half) * (1.0 - 2.0 * overlap))


def row_overlap(fov_deg: float, yaw_step: float) -> float:
    """Centre-row pixel overlap of two views ``yaw_step`` radians apart (inverse of :func:`yaw_step_for_overlap`)."""
    half = math.radians(fov_deg) / 2.0
    return max(0.0, 0.5 * (1.0 - math.tan(yaw_step - half) / math.tan(half)))


def camera_to_world(yaw: float, pitch: float) -> np.ndarray:
    """[3, 3] camera-to-world rotation of a view with ``yaw`` and ``pitch`` (radians)."""
    return rotation_y(yaw) @ rotation_x(pitch)


def equirectangular_directions(width: int, height: int) -> np.ndarray:
    """[H, W, 3] unit world direction of every pixel centre of an equirectangular image."""
    lon = ((np.arange(width) + 0.5) / width - 0.5) * 2.0 * np.pi
    lat = (0.5 - (np.arange(height) + 0.5) / height) * np.pi
    lon, lat = np.meshgrid(lon, lat)
    return np.stack([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)], axis=-1)


def view_rays(camera: Camera) -> np.ndarray:
    """[H, W, 3] camera-frame rays (z = 1) through the pixel centres of a pinhole camera."""
    fx, fy, cx, cy = camera.intrinsics()
    # COLMAP's pixel convention: the centre of the top-left pixel is at (0.5, 0.5).
    x = (np.arange(camera.width) + 0.5 - cx) / fx
    y = (np.arange(camera.height) + 0.5 - cy) / fy
    x, y = np.meshgrid(x, y)
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def sample_equirectangular(panorama: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``panorama`` [Hp, Wp(, C)] along world ``directions`` [H, W, 3]."""
    import cv2

    height, width = panorama.shape[:2]
    d = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    lon = np.arctan2(d[..., 0], d[..., 2])
    lat = np.arcsin(np.clip(-d[..., 1], -1.0, 1.0))
    u = (lon / (2.0 * np.pi) + 0.5) * width - 0.5
    v = (0.5 - lat / np.pi) * height - 0.5
    pad = 2
    # Wrap longitude, clamp latitude: remap's own border modes act on both axes at once.
    padded = cv2.copyMakeBorder(panorama, pad, pad, 0, 0, cv2.BORDER_REPLICATE)
    padded = cv2.copyMakeBorder(padded, 0, 0, pad, pad, cv2.BORDER_WRAP)
    return cv2.remap(padded, (u + pad).astype(np.float32), (v + pad).astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def panorama_views(options: PanoramaOptions) -> tuple[Camera, list[tuple[str, np.ndarray]], dict[str, Any]]:
    """The shared PINHOLE camera and (name, camera-to-world [3, 3]) of every view, plus layout facts."""
    options.validate()
    focal = focal_from_fov(options.width, options.fov_deg)
    camera = Camera(1, "PINHOLE", options.width, options.height, np.array([focal, focal, options.width / 2.0, options.height / 2.0]))
    wanted_step = yaw_step_for_overlap(options.fov_deg, options.overlap)
    count = max(1, math.ceil(2.0 * math.pi / wanted_step - 1e-9))
    step = 2.0 * math.pi / count
    views = []
    for row, pitch_deg in enumerate(options.pitches_deg):
        for column in range(count):
            name = f"view_r{row:02d}_c{column:03d}.png"
            views.append((name, camera_to_world(column * step, math.radians(pitch_deg))))
    vertical_fov = 2.0 * math.degrees(math.atan(options.height / 2.0 / focal))
    layout = {
        "views_per_row": count,
        "rows": len(options.pitches_deg),
        "yaw_step_deg": math.degrees(step),
        "overlap": row_overlap(options.fov_deg, step),
        "fov_deg": options.fov_deg,
        "vertical_fov_deg": vertical_fov,
        "focal_px": focal,
    }
    return camera, views, layout


def _is_equirectangular(width: int, height: int) -> bool:
    return abs(width / height - 2.0) < 0.02


def scene_from_panorama(
    panorama_path: str | Path,
    out_dir: str | Path,
    options: PanoramaOptions | None = None,
    progress: ProgressCallback = no_progress,
) -> dict[str, Any]:
    """Cut a panorama into a scene folder; returns (and saves as ``panorama_report.json``) a report.

    Equirectangular input: ``out_dir/images/view_rRR_cCCC.png`` pinhole views and
    ``out_dir/sparse/0`` with their exact camera (PINHOLE) and rotations, all centres at the
    origin. One station has no parallax: the geometry of such a scene must come from priors.
    Flat strip: overlapping crops in ``out_dir/images`` and no model (run SfM on them if the
    strip was taken from several places). Built atomically.
    """
    from ..colmap.io import write_model
    from ..formats.imageio import read_image, write_png
    from ..io_utils import atomic_directory, atomic_write_json

    options = options or PanoramaOptions()
    options.validate()
    panorama_path = Path(panorama_path)
    panorama = read_image(panorama_path)
    height, width = panorama.shape[:2]
    equirectangular = _is_equirectangular(width, height) if options.equirectangular is None else options.equirectangular
    report: dict[str, Any] = {"source": str(panorama_path), "panorama_size": [width, height]}
    with atomic_directory(out_dir, overwrite=options.overwrite) as staging:
        staged = SceneDir(staging)
        staged.images.mkdir()
        if equirectangular:
            camera, views, layout = panorama_views(options)
            report.update(layout, kind="equirectangular", model="sparse/0 (rotation-only station, exact cameras)")
            pixels_per_degree = width / 360.0
            view_pixels_per_degree = camera.params[0] * math.radians(1.0)
            if view_pixels_per_degree > 1.05 * pixels_per_degree:
                report["note_resolution"] = (
                    f"views sample {view_pixels_per_degree:.1f} px/deg but the panorama has {pixels_per_degree:.1f} px/deg: "
                    "they are upsampled (use a smaller --size or a wider --fov-deg)"
                )
            rays = view_rays(camera)
            names, rotations = [], []
            for step, (name, to_world) in enumerate(views):
                write_png(staged.image(name), sample_equirectangular(panorama, rays @ to_world.T))
                names.append(name)
                rotations.append(to_world.T)
                progress(ProgressEvent(step + 1, len(views), stage="panorama"))
            model = station_model(camera, names, rotations, source=str(SceneDir(out_dir).model))
            write_model(model, staged.model, binary=True)
        else:
            report.update(_cut_strip(panorama, staged.images, options, progress))
        report["limits"] = (
            "all views share one camera centre: no parallax, so depth cannot be triangulated; "
            "geometry must come from priors (or from images taken at other positions)"
            if equirectangular
            else "a flat strip has no known projection: crops only, no camera model; run `esgs dataset from-images` "
            "on them if the strip was taken from several positions"
        )
        atomic_write_json(staging / "panorama_report.json", report)
        names = sorted(p.name for p in staged.images.iterdir())
        atomic_write_json(staged.provenance, scene_provenance(
            "panorama" if equirectangular else "strip", names, units="none: one station, no scale", points3d=0,
            report="panorama_report.json", extra={"panorama": str(panorama_path)}))
    return report


def _cut_strip(strip: np.ndarray, images_dir: Path, options: PanoramaOptions, progress: ProgressCallback) -> dict[str, Any]:
    """Overlapping crops of the requested aspect across a flat strip (and down it, when taller)."""
    from ..formats.imageio import write_png

    height, width = strip.shape[:2]
    scale = min(1.0, height / options.height, width / options.width)
    crop_w, crop_h = max(1, int(options.width * scale)), max(1, int(options.height * scale))

    def starts(total: int, size: int) -> list[int]:
        if size >= total:
            return [0]
        count = math.ceil((total - size) / (size * (1.0 - options.overlap))) + 1
        return [round(i * (total - size) / (count - 1)) for i in range(count)]

    xs, ys = starts(width, crop_w), starts(height, crop_h)
    if len(xs) * len(ys) < 2:
        raise DatasetError(
            f"the strip ({width}x{height}) fits in a single {crop_w}x{crop_h} crop", hint="use a smaller --size"
        )
    total, step = len(xs) * len(ys), 0
    for row, y in enumerate(ys):
        for column, x in enumerate(xs):
            write_png(images_dir / f"crop_r{row:02d}_c{column:03d}.png", strip[y : y + crop_h, x : x + crop_w])
            step += 1
            progress(ProgressEvent(step, total, stage="strip"))
    actual = 1.0 - (xs[1] - xs[0]) / crop_w if len(xs) > 1 else 0.0
    return {"kind": "strip", "crop_size": [crop_w, crop_h], "crops": total, "overlap": actual, "model": "none"}
