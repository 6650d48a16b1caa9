"""Read and write COLMAP sparse models (binary or text) through pycolmap.

Reading is two-staged so that no input, however corrupt, can crash the process:
:mod:`.parse` reads and checks every byte in Python/numpy, :mod:`.validate` checks the
references between records, and only then does pycolmap read the very same bytes (copied
into a private folder holding just ``cameras``/``images``/``points3D``; pycolmap 4's
optional ``rigs``/``frames`` records carry nothing our dataclasses keep: images.bin/txt hold
the registered images with their poses).
"""
from __future__ import annotations

import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import DatasetError
from ..io_utils import atomic_directory
from ..formats.scene_dir import SceneDir
from . import parse
from .model import Camera, ColmapModel, Image, Point3D
from .validate import check_references, check_registered

if TYPE_CHECKING:  # pycolmap is imported lazily: it is heavy and only needed here
    import pycolmap

MODEL_FILES = ("cameras", "images", "points3D")
_BINARY_READERS = {
    "cameras": parse.read_cameras_binary,
    "images": parse.read_images_binary,
    "points3D": parse.read_points3d_binary,
}
_TEXT_READERS = {
    "cameras": parse.read_cameras_text,
    "images": parse.read_images_text,
    "points3D": parse.read_points3d_text,
}


def find_model_dir(path: str | Path) -> tuple[Path, str]:
    """Locate the model files under ``path``; return (folder, "bin" | "txt").

    ``path`` may be a model folder (``cameras.bin``... or ``cameras.txt``...), a scene
    folder holding ``sparse/0/`` or a folder holding ``sparse/`` with the files directly.
    Binary wins when both complete sets are present (as in COLMAP).
    """
    path = Path(path)
    if not path.exists():
        raise DatasetError("COLMAP model folder does not exist", path=path)
    if not path.is_dir():
        raise DatasetError("expected a COLMAP model folder, got a file", path=path, hint="pass the folder holding cameras/images/points3D")
    folder_of = SceneDir(path)
    candidates = [path, folder_of.model, folder_of.sparse]
    for folder in candidates:
        for extension in ("bin", "txt"):
            if all((folder / f"{name}.{extension}").is_file() for name in MODEL_FILES):
                return folder, extension
    for folder in candidates:
        for extension in ("bin", "txt"):
            present = [name for name in MODEL_FILES if (folder / f"{name}.{extension}").is_file()]
            if present:
                missing = [f"{name}.{extension}" for name in MODEL_FILES if name not in present]
                raise DatasetError(
                    f"incomplete COLMAP model: {', '.join(missing)} missing",
                    path=folder,
                    hint="a model needs cameras, images and points3D files of one format",
                )
    raise DatasetError(
        "no COLMAP model found (looked for cameras/images/points3D .bin or .txt here, in sparse/0 and in sparse)",
        path=path,
        hint="point at the model folder or at a scene folder holding sparse/0",
    )


def parse_model(path: str | Path) -> ColmapModel:
    """Read a model with the project's own checked parsers only (no pycolmap).

    Every structural problem and broken reference is a DatasetError naming the file.
    """
    folder, extension = find_model_dir(path)
    blobs = {name: parse.read_bytes(folder / f"{name}.{extension}") for name in MODEL_FILES}
    return _parse_blobs(folder, extension, blobs)


def _parse_blobs(folder: Path, extension: str, blobs: dict[str, bytes]) -> ColmapModel:
    readers = _BINARY_READERS if extension == "bin" else _TEXT_READERS
    cameras = readers["cameras"](folder / f"cameras.{extension}", blobs["cameras"])
    images = readers["images"](folder / f"images.{extension}", blobs["images"])
    points = readers["points3D"](folder / f"points3D.{extension}", blobs["points3D"])
    model = ColmapModel(cameras, images, points, source=str(folder))
    check_references(model, folder)
    return model


def read_model(path: str | Path, *, use_pycolmap: bool = False) -> ColmapModel:
    """Read a COLMAP sparse model (binary or text) into the project's dataclasses.

    ``path``: a model folder or a scene folder holding ``sparse/0``. The files are fully
    checked before pycolmap reads them; any problem (missing or truncated file, corrupt
    record, image naming an unknown camera, inconsistent tracks, no registered image)
    raises :class:`DatasetError` naming the file and what is wrong.

    The model returned is the checked parse itself, read once (the default everywhere: the
    add-on, training, priors, the CLI). ``use_pycolmap=True`` also hands the same bytes to
    pycolmap and returns its reading, after checking the counts agree: the tests' cross-check
    that both readers see the same model (pycolmap's per-point Python objects cost ~25 us per
    3D point to convert, ~25 s for a 1M-point model).
    """
    folder, extension = find_model_dir(path)
    # Read each file once: the bytes checked are the bytes pycolmap gets, even if the
    # files change meanwhile.
    blobs = {name: parse.read_bytes(folder / f"{name}.{extension}") for name in MODEL_FILES}
    checked = _parse_blobs(folder, extension, blobs)
    check_registered(checked)
    if not use_pycolmap:
        return checked
    import pycolmap

    with tempfile.TemporaryDirectory(prefix="esgs_colmap_") as staging:
        for name, data in blobs.items():
            (Path(staging) / f"{name}.{extension}").write_bytes(data)
        reconstruction = pycolmap.Reconstruction()
        try:
            if extension == "bin":
                reconstruction.read_binary(staging)
            else:
                reconstruction.read_text(staging)
        except Exception as error:  # pycolmap raises RuntimeError/ValueError/IndexError...
            raise DatasetError(f"pycolmap could not read the model: {error}", path=folder) from error
    model = from_pycolmap(reconstruction, source=str(folder))
    if (len(model.cameras), len(model.images), len(model.points)) != (
        len(checked.cameras),
        len(checked.images),
        len(checked.points),
    ):
        raise DatasetError(
            "pycolmap and the file parser disagree on the number of cameras/images/points",
            path=folder,
            hint="please report this model as a bug",
        )
    return model


def from_pycolmap(reconstruction: "pycolmap.Reconstruction", source: str = "") -> ColmapModel:
    """Convert a ``pycolmap.Reconstruction`` into a :class:`ColmapModel` (registered images only)."""
    cameras = {}
    for camera_id, camera in reconstruction.cameras.items():
        cameras[int(camera_id)] = Camera(
            int(camera_id), camera.model.name, int(camera.width), int(camera.height), np.array(camera.params, dtype=np.float64)
        )
    images = {}
    for image_id, image in reconstruction.images.items():
        if not image.has_pose:
            continue
        pose = image.cam_from_world()
        x, y, z, w = np.asarray(pose.rotation.quat, dtype=np.float64)  # pycolmap stores xyzw
        points2d = image.points2D
        xy = np.array([point.xy for point in points2d], dtype=np.float64).reshape(-1, 2)
        ids = np.full(len(points2d), -1, dtype=np.int64)  # -1: no 3D point
        observed = image.get_observation_point2D_idxs()
        if observed:
            ids[np.asarray(observed, dtype=np.int64)] = [point.point3D_id for point in image.get_observation_points2D()]
        images[int(image_id)] = Image(
            int(image_id), image.name, int(image.camera_id), np.array([w, x, y, z]), np.asarray(pose.translation, dtype=np.float64).copy(), xy, ids
        )
    points = {}
    for point_id, point in reconstruction.points3D.items():
        elements = point.track.elements
        points[int(point_id)] = Point3D(
            int(point_id),
            np.asarray(point.xyz, dtype=np.float64).copy(),
            np.asarray(point.color, dtype=np.uint8).copy(),
            float(point.error),
            np.array([element.image_id for element in elements], dtype=np.int64),
            np.array([element.point2D_idx for element in elements], dtype=np.int64),
        )
    return ColmapModel(cameras, images, points, source=source)


def to_pycolmap(model: ColmapModel) -> "pycolmap.Reconstruction":
    """Build a ``pycolmap.Reconstruction`` (trivial rigs and frames) from a :class:`ColmapModel`.

    The model's references are checked first, so pycolmap never sees a broken model.
    """
    import pycolmap

    _check_writable(model)
    reconstruction = pycolmap.Reconstruction()
    for camera_id in sorted(model.cameras):
        camera = model.cameras[camera_id]
        reconstruction.add_camera_with_trivial_rig(
            pycolmap.Camera(
                camera_id=camera_id,
                model=camera.model,
                width=int(camera.width),
                height=int(camera.height),
                params=np.asarray(camera.params, dtype=np.float64),
            )
        )
    for image_id in sorted(model.images):
        image = model.images[image_id]
        # Observations are attached through the points' tracks below; pycolmap fills the ids.
        pycolmap_image = pycolmap.Image(
            name=image.name,
            keypoints=np.asarray(image.points2d, dtype=np.float64).reshape(-1, 2),
            camera_id=int(image.camera_id),
            image_id=int(image_id),
        )
        w, x, y, z = np.asarray(image.quat_wxyz, dtype=np.float64) / np.linalg.norm(image.quat_wxyz)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([x, y, z, w])), np.asarray(image.translation, dtype=np.float64))
        reconstruction.add_image_with_trivial_frame(pycolmap_image, pose)
    for point_id in sorted(model.points):
        point = model.points[point_id]
        track = pycolmap.Track()
        for image_id, index in zip(point.track_image_ids.tolist(), point.track_point2d_idxs.tolist()):
            track.add_element(int(image_id), int(index))
        record = pycolmap.Point3D()
        record.xyz = np.asarray(point.xyz, dtype=np.float64)
        record.color = np.asarray(point.rgb, dtype=np.uint8)
        record.error = float(point.error)
        record.track = track
        reconstruction.add_point3D_with_id(int(point_id), record)
    return reconstruction


def _check_writable(model: ColmapModel) -> None:
    from .camera_models import model_info

    for camera in model.cameras.values():
        info = model_info(camera.model)
        if np.asarray(camera.params).reshape(-1).shape[0] != info.num_params:
            raise DatasetError(f"camera {camera.camera_id}: model {info.name} takes {info.num_params} parameters, got {len(camera.params)}")
    for image in model.images.values():
        if not (np.all(np.isfinite(image.quat_wxyz)) and np.linalg.norm(image.quat_wxyz) > 0):
            raise DatasetError(f"image {image.image_id} ({image.name}) has an invalid rotation quaternion")
        problem = parse.image_name_problem(image.name)
        if problem:
            raise DatasetError(f"image {image.image_id} name {image.name!r} {problem}")
    check_references(model)


def write_model(model: ColmapModel, path: str | Path, binary: bool = True, *, overwrite: bool = False) -> Path:
    """Write ``model`` as a COLMAP model folder (``.bin`` or ``.txt`` files) atomically.

    The folder is built beside ``path`` and renamed into place when complete; pycolmap
    also writes its ``rigs``/``frames`` files (trivial rigs, one frame per image).
    An existing empty folder is replaced; a non-empty one only with ``overwrite``.
    Returns ``path``.
    """
    path = Path(path)
    if not binary:
        spaced = [image.name for image in model.images.values() if " " in image.name]
        if spaced:
            raise DatasetError(
                f"image names with spaces cannot be stored in COLMAP text files: {spaced[:5]}",
                path=path,
                hint="write the binary format or rename the images",
            )
    reconstruction = to_pycolmap(model)
    if path.is_dir() and not any(path.iterdir()):
        path.rmdir()
    with atomic_directory(path, overwrite=overwrite) as staging:
        if binary:
            reconstruction.write_binary(str(staging))
        else:
            reconstruction.write_text(str(staging))
    return path


def load_scene(scene_dir: str | Path, *, check_sizes: bool = False) -> tuple[ColmapModel, Path]:
    """Read a scene folder (``images/`` + ``sparse/0``): return (model, images folder).

    Checks that every image of the model exists; with ``check_sizes`` also that each
    image file's size matches its camera (decodes every image: slower).
    """
    from .validate import check_image_sizes, validate_images

    scene_dir = Path(scene_dir)
    model = read_model(scene_dir)
    images_dir = SceneDir(scene_dir).images
    validate_images(model, images_dir)
    if check_sizes:
        check_image_sizes(model, images_dir)
    return model, images_dir
