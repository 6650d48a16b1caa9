"""Small pieces shared by the dataset builders: image listing, rotations, model assembly."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..colmap.geometry import matrix_to_quat_wxyz
from ..colmap.model import Camera, ColmapModel, Image
from ..errors import DatasetError
from ..formats.scene_dir import SceneDir

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


def list_images(images_dir: str | Path) -> list[Path]:
    """Image files directly inside ``images_dir``, sorted by name; a clear error when there are none."""
    images_dir = Path(images_dir)
    if not images_dir.is_dir():
        raise DatasetError("image folder not found", path=images_dir, hint="give a folder of PNG/JPEG images")
    files = sorted(p for p in images_dir.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise DatasetError("no images (.png, .jpg, .tif, .bmp) in the folder", path=images_dir)
    return files


def check_readable(files: list[Path]) -> list[tuple[int, int]]:
    """Decode every image once; raise one DatasetError naming all unreadable files. Returns (width, height)s."""
    from ..formats.imageio import read_image

    sizes, bad = [], []
    for path in files:
        try:
            pixels = read_image(path)
            sizes.append((int(pixels.shape[1]), int(pixels.shape[0])))
        except DatasetError as error:
            bad.append(f"{path.name} ({error})")
    if bad:
        raise DatasetError(
            f"{len(bad)} of {len(files)} images cannot be read: " + "; ".join(bad[:5]) + (" ..." if len(bad) > 5 else ""),
            path=files[0].parent,
            hint="remove or re-export these files (PNG or JPEG) and run again",
        )
    return sizes


def rotation_x(angle: float) -> np.ndarray:
    """[3, 3] rotation about x by ``angle`` radians (right-handed)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rotation_y(angle: float) -> np.ndarray:
    """[3, 3] rotation about y by ``angle`` radians (right-handed)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def station_model(camera: Camera, names: list[str], world_to_camera: list[np.ndarray], source: str = "") -> ColmapModel:
    """A rotation-only COLMAP model: one shared camera, every centre at the origin (translation 0).

    world_to_camera: one [3, 3] rotation per name.
    """
    images = {}
    for index, (name, rotation) in enumerate(zip(names, world_to_camera), start=1):
        images[index] = Image(index, name, camera.camera_id, matrix_to_quat_wxyz(np.asarray(rotation, dtype=np.float64)), np.zeros(3))
    return ColmapModel({camera.camera_id: camera}, images, {}, source=source)


def scene_provenance(source: str, images: list[str], *, units: str, points3d: int, report: str, extra: dict | None = None) -> dict:
    """The ``scene.json`` record of a scene folder built from real images (see docs/scene_format.md)."""
    from ... import __version__

    record = {
        "format": "esgs-scene",
        "format_version": 1,
        "source": source,
        "generator": f"esgs.core.datasets ({source})",
        "esgs_version": __version__,
        "units": units,
        "camera_frame": "opencv (x right, y down, z forward); poses world-to-camera as COLMAP",
        "images": sorted(images),
        # the model's path relative to the scene folder ("sparse/0")
        "sparse": SceneDir(Path()).model.as_posix() if source != "strip" else None,
        "points3d": int(points3d),
        "report": report,
    }
    record.update(extra or {})
    return record
