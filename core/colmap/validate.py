"""Checks on a COLMAP model and the images beside it, with errors that say what to fix."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DatasetError
from .model import ColmapModel


def check_references(model: ColmapModel, path: str | Path | None = None) -> None:
    """Check that every reference inside ``model`` points at something that exists.

    - every image's camera id is a known camera;
    - every track element (image id, 2D point index) names a known image and one of its
      2D points, and that 2D point refers back to the same 3D point;
    - every 2D point that names a 3D point is in that point's track.

    COLMAP keeps these invariants; pycolmap may abort the process when they are broken,
    so they are checked before pycolmap sees the files. ``path`` is the model folder
    named in messages (defaults to ``model.source``).
    """
    where = Path(path) if path is not None else (Path(model.source) if model.source else None)
    for image in model.images.values():
        if image.camera_id not in model.cameras:
            raise DatasetError(
                f"image {image.image_id} ({image.name}) refers to camera {image.camera_id}, "
                f"which is not in the cameras file (known: {sorted(model.cameras)})",
                path=where,
                hint="the model is inconsistent; re-export it from COLMAP",
            )
        if len(image.points2d) != len(image.point3d_ids):
            raise DatasetError(f"image {image.image_id} has {len(image.points2d)} 2D points but "
                               f"{len(image.point3d_ids)} 3D point ids", path=where)

    # (point id, image id, 2D index) seen from the tracks and from the images must agree.
    point_ids = np.fromiter(model.points.keys(), dtype=np.int64, count=len(model.points))
    track_images = [point.track_image_ids for point in model.points.values()]
    track_indices = [point.track_point2d_idxs for point in model.points.values()]
    lengths = np.array([len(ids) for ids in track_images], dtype=np.int64)
    if any(len(ids) != len(indices) for ids, indices in zip(track_images, track_indices)):
        bad = next(p for p in model.points.values() if len(p.track_image_ids) != len(p.track_point2d_idxs))
        raise DatasetError(f"3D point {bad.point3d_id} has a malformed track", path=where)
    if len(point_ids) and lengths.sum():
        from_tracks = np.stack(
            [
                np.repeat(point_ids, lengths),
                np.concatenate(track_images).astype(np.int64),
                np.concatenate(track_indices).astype(np.int64),
            ],
            axis=1,
        )
    else:
        from_tracks = np.zeros((0, 3), np.int64)
    image_ids = np.array(sorted(model.images), dtype=np.int64)
    num_points2d = np.array([len(model.images[int(i)].point3d_ids) for i in image_ids], dtype=np.int64)
    if len(image_ids):
        slot = np.clip(np.searchsorted(image_ids, from_tracks[:, 1]), 0, len(image_ids) - 1)
        known = image_ids[slot] == from_tracks[:, 1]
    else:
        slot = np.zeros(len(from_tracks), np.int64)
        known = np.zeros(len(from_tracks), bool)
    if not np.all(known):
        point_id, image_id, _ = from_tracks[np.argmin(known)].tolist()
        raise DatasetError(
            f"3D point {point_id} is observed in image {image_id}, which is not in the images file",
            path=where,
            hint="the model is inconsistent; re-export it from COLMAP",
        )
    in_range = (from_tracks[:, 2] >= 0) & (from_tracks[:, 2] < num_points2d[slot])
    if not np.all(in_range):
        point_id, image_id, index = from_tracks[np.argmin(in_range)].tolist()
        raise DatasetError(
            f"3D point {point_id} is observed as 2D point {index} of image {image_id}, "
            f"which has only {len(model.images[image_id].point3d_ids)} 2D points",
            path=where,
            hint="the model is inconsistent; re-export it from COLMAP",
        )
    image_triples = []
    for image in model.images.values():
        observed = np.flatnonzero(np.asarray(image.point3d_ids) >= 0)
        if len(observed):
            image_triples.append(
                np.stack([np.asarray(image.point3d_ids)[observed], np.full(len(observed), image.image_id, np.int64), observed], axis=1)
            )
    from_tracks = _sorted_rows([from_tracks])
    from_images = _sorted_rows(image_triples)
    if from_tracks.shape != from_images.shape or not np.array_equal(from_tracks, from_images):
        mismatch = _first_difference(from_tracks, from_images)
        raise DatasetError(
            f"3D point tracks and image observations disagree ({len(from_tracks)} track elements, "
            f"{len(from_images)} observations; first difference: {mismatch})",
            path=where,
            hint="the model is inconsistent; re-export it from COLMAP",
        )


def _sorted_rows(parts: list[np.ndarray]) -> np.ndarray:
    if not parts:
        return np.zeros((0, 3), np.int64)
    rows = np.concatenate(parts).astype(np.int64)
    return rows[np.lexsort(rows.T[::-1])]


def _first_difference(a: np.ndarray, b: np.ndarray) -> str:
    for row_a, row_b in zip(a.tolist(), b.tolist()):
        if row_a != row_b:
            return f"point {row_a[0]} in image {row_a[1]} at 2D index {row_a[2]} vs point {row_b[0]} in image {row_b[1]} at {row_b[2]}"
    longer, label = (a, "track") if len(a) > len(b) else (b, "image")
    row = longer[min(len(a), len(b))].tolist()
    return f"{label} entry point {row[0]} in image {row[1]} at 2D index {row[2]} has no counterpart"


def check_registered(model: ColmapModel) -> None:
    """A model must hold at least one registered image to be of any use."""
    if not model.images:
        raise DatasetError(
            "the model has no registered images",
            path=model.source or None,
            hint="COLMAP could not register any image; check the images' overlap and rerun the mapper",
        )


def validate_images(model: ColmapModel, images_dir: str | Path) -> list[Path]:
    """Check every image of ``model`` exists under ``images_dir``; return their paths in name order.

    Raises one DatasetError listing (up to ten of) the missing files.
    """
    from .parse import image_name_problem

    images_dir = Path(images_dir)
    if not images_dir.is_dir():
        raise DatasetError("image folder does not exist", path=images_dir, hint="point at the folder holding the images")
    for image in model.images.values():
        problem = image_name_problem(image.name)
        if problem:
            raise DatasetError(f"image {image.image_id} name {image.name!r} {problem}", path=images_dir)
    paths = [images_dir / image.name for image in model.sorted_images()]
    missing = [path for path in paths if not path.is_file()]
    if missing:
        shown = ", ".join(path.relative_to(images_dir).as_posix() for path in missing[:10])
        more = f" and {len(missing) - 10} more" if len(missing) > 10 else ""
        raise DatasetError(
            f"{len(missing)} of {len(paths)} images named in the COLMAP model are missing: {shown}{more}",
            path=images_dir,
            hint="copy the images there or point at the right image folder",
        )
    return paths


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file; DatasetError when it cannot be decoded."""
    from ..formats.imageio import read_image

    array = read_image(path)
    return int(array.shape[1]), int(array.shape[0])


def check_image_sizes(model: ColmapModel, images_dir: str | Path) -> None:
    """Check each image file's size equals its camera's width x height.

    Catches images resized after reconstruction and cameras shared by images of
    different sizes; the message lists the offending files.
    """
    images_dir = Path(images_dir)
    validate_images(model, images_dir)
    wrong = []
    for image in model.sorted_images():
        camera = model.cameras[image.camera_id]
        width, height = image_size(images_dir / image.name)
        if (width, height) != (camera.width, camera.height):
            wrong.append(f"{image.name} is {width} x {height}, camera {camera.camera_id} says {camera.width} x {camera.height}")
    if wrong:
        shown = "; ".join(wrong[:10])
        more = f" and {len(wrong) - 10} more" if len(wrong) > 10 else ""
        raise DatasetError(
            f"{len(wrong)} images do not match their camera's size: {shown}{more}",
            path=images_dir,
            hint="use the images the model was reconstructed from (not resized copies)",
        )
