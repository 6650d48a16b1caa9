"""Independent, defensive parsers of COLMAP's sparse-model files.

pycolmap (C++) may abort the whole process on malformed input, so every file is parsed
and checked here first, in numpy/struct, and only handed to pycolmap when its structure
is sound. Each parser returns the project's dataclasses; :mod:`.validate` then checks the
cross references (cameras of images, tracks of points).

Binary layout (little endian), as COLMAP writes it:

- ``cameras.bin``: u64 count; per camera u32 id, i32 model id, u64 width, u64 height,
  f64 params[P(model)].
- ``images.bin``: u64 count; per image u32 id, f64 qvec[4] (w, x, y, z), f64 tvec[3],
  u32 camera id, NUL-terminated name, u64 M, M x (f64 x, f64 y, u64 point3D id).
- ``points3D.bin``: u64 count; per point u64 id, f64 xyz[3], u8 rgb[3], f64 error,
  u64 L, L x (u32 image id, u32 point2D index).

The text files hold the same records, one per line (images take two lines), with ``#``
comments. Every reader takes the file's ``path`` (named in errors) and optionally its
already-read ``data``, so a caller can check exactly the bytes it hands on.
"""
from __future__ import annotations

import math
import re
import struct
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from .camera_models import CAMERA_MODELS, CAMERA_MODELS_BY_ID
from .model import Camera, Image, Point3D

#: COLMAP's "no 3D point" marker for a 2D observation in binary files (u64 max).
INVALID_POINT3D_ID_BINARY = 2**64 - 1
#: COLMAP's invalid camera / image id (u32 max); never a real id.
INVALID_ID_32 = 2**32 - 1
#: Larger than any real sensor; anything above is a corrupt field, not a camera.
MAX_IMAGE_SIDE = 1_000_000

_CAMERA_HEAD = struct.Struct("<IiQQ")
_IMAGE_HEAD = struct.Struct("<I4d3dI")
_POINT_HEAD = struct.Struct("<Q3d3BdQ")
_U64 = struct.Struct("<Q")
_OBSERVATION_DTYPE = np.dtype([("xy", "<f8", (2,)), ("point3d_id", "<u8")])
_TRACK_DTYPE = np.dtype([("image_id", "<u4"), ("point2d_idx", "<u4")])

# Strict number syntax: what both Python and C++ (std::stod/stoi) read the same way.
# Atomic groups and possessive repeats keep the whole-line patterns linear on bad input.
_INT = r"(?>[+-]?[0-9]++)"
_FLOAT = r"(?>[+-]?(?:[0-9]++(?:\.[0-9]*+)?|\.[0-9]++)(?:[eE][+-]?[0-9]++)?)"
_INT_RE = re.compile(_INT)
_FLOAT_RE = re.compile(_FLOAT)
# COLMAP splits text records on single spaces; so do we, so both readers agree.
_OBSERVATIONS_RE = re.compile(rf"(?:{_FLOAT} {_FLOAT} {_INT}(?: {_FLOAT} {_FLOAT} {_INT})*+)?")
_TRACK_RE = re.compile(rf"(?:{_INT} {_INT}(?: {_INT} {_INT})*+)?")
_LINE_TRIM = " \t\r\v\f"


# --------------------------------------------------------------------------------------
# binary


def read_bytes(path: Path) -> bytes:
    """A model file's bytes; DatasetError when it cannot be read."""
    try:
        return path.read_bytes()
    except OSError as error:
        raise DatasetError(f"cannot read file: {error.strerror or error}", path=path) from error


class _Reader:
    """Bounds-checked cursor over a file's bytes; every overrun is a DatasetError."""

    def __init__(self, path: Path, data: bytes | None = None):
        self.path = path
        self.data = read_bytes(path) if data is None else data
        self.pos = 0

    def remaining(self) -> int:
        return len(self.data) - self.pos

    def need(self, size: int, what: str) -> None:
        if size > self.remaining():
            raise DatasetError(
                f"file is truncated: {what} needs {size} bytes at offset {self.pos}, "
                f"only {self.remaining()} left",
                path=self.path,
                hint="re-export the model from COLMAP",
            )

    def unpack(self, layout: struct.Struct, what: str) -> tuple:
        self.need(layout.size, what)
        values = layout.unpack_from(self.data, self.pos)
        self.pos += layout.size
        return values

    def array(self, dtype: np.dtype, count: int, what: str) -> np.ndarray:
        self.need(count * dtype.itemsize, what)
        values = np.frombuffer(self.data, dtype=dtype, count=count, offset=self.pos)
        self.pos += count * dtype.itemsize
        return values

    def count(self, record_min_size: int, what: str) -> int:
        (count,) = self.unpack(_U64, f"the number of {what}")
        # A corrupt count must not send us looping over billions of records.
        if count * record_min_size > self.remaining():
            raise DatasetError(
                f"header announces {count} {what} but the file is too short for them",
                path=self.path,
                hint="the file is truncated or corrupt; re-export the model",
            )
        return count

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise DatasetError(f"file is truncated inside {what}", path=self.path)
        raw = self.data[self.pos : end]
        self.pos = end + 1
        return _check_name(raw, self.path, what)

    def finish(self) -> None:
        if self.remaining():
            raise DatasetError(
                f"{self.remaining()} unexpected bytes after the last record (offset {self.pos})",
                path=self.path,
                hint="the file is corrupt; re-export the model",
            )


def image_name_problem(name: str) -> str | None:
    """Why ``name`` cannot be an image name of a scene folder, or None when it can.

    Names are paths relative to the image folder; an absolute path or a ``..`` component
    would make readers and writers (undistortion, dataset export) leave that folder.
    """
    if not name:
        return "is empty"
    if any(ord(char) < 32 or ord(char) == 127 for char in name):
        return "holds control characters"
    if name.startswith(("/", "\\")) or re.match(r"[A-Za-z]:", name):
        return "is an absolute path"
    if ".." in re.split(r"[/\\]", name):
        return "climbs out of the image folder ('..')"
    return None


def _check_name(raw: bytes, path: Path, what: str) -> str:
    try:
        name = raw.decode("utf-8")
    except UnicodeDecodeError as error:
        raise DatasetError(f"{what} is not valid UTF-8", path=path) from error
    problem = image_name_problem(name)
    if problem:
        raise DatasetError(f"{what} {name!r} {problem}", path=path, hint="image names must be relative paths inside the image folder")
    return name


def _fail(path: Path, message: str, hint: str | None = "the file is corrupt; re-export the model") -> DatasetError:
    return DatasetError(message, path=path, hint=hint)


def _check_camera(camera: Camera, path: Path) -> None:
    if not (0 < camera.width <= MAX_IMAGE_SIDE and 0 < camera.height <= MAX_IMAGE_SIDE):
        raise _fail(path, f"camera {camera.camera_id} has an impossible size {camera.width} x {camera.height}")
    if not np.all(np.isfinite(camera.params)):
        raise _fail(path, f"camera {camera.camera_id} has non-finite parameters {camera.params.tolist()}")


def _check_pose(image: Image, path: Path) -> None:
    if not (np.all(np.isfinite(image.quat_wxyz)) and np.all(np.isfinite(image.translation))):
        raise _fail(path, f"image {image.image_id} ({image.name}) has a non-finite pose")
    norm = float(np.linalg.norm(image.quat_wxyz))
    if not 1e-6 < norm < 1e6:
        raise _fail(path, f"image {image.image_id} ({image.name}) has a degenerate rotation quaternion")
    if not np.all(np.isfinite(image.points2d)):
        raise _fail(path, f"image {image.image_id} ({image.name}) has non-finite 2D points")


def _check_unique(kind: str, key: int | str, seen: set, path: Path) -> None:
    if key in seen:
        raise _fail(path, f"{kind} {key!r} appears twice")
    seen.add(key)


def read_cameras_binary(path: Path, data: bytes | None = None) -> dict[int, Camera]:
    """Parse and check ``cameras.bin``."""
    reader = _Reader(path, data)
    count = reader.count(_CAMERA_HEAD.size, "cameras")
    cameras: dict[int, Camera] = {}
    for _ in range(count):
        camera_id, model_id, width, height = reader.unpack(_CAMERA_HEAD, "a camera record")
        info = CAMERA_MODELS_BY_ID.get(model_id)
        if info is None:
            raise _fail(path, f"camera {camera_id} has unknown model id {model_id}")
        if camera_id == INVALID_ID_32 or camera_id in cameras:
            raise _fail(path, f"camera id {camera_id} is invalid or appears twice")
        params = reader.array(np.dtype("<f8"), info.num_params, f"camera {camera_id} parameters").astype(np.float64)
        camera = Camera(camera_id, info.name, int(width), int(height), params)
        _check_camera(camera, path)
        cameras[camera_id] = camera
    reader.finish()
    return cameras


def read_images_binary(path: Path, data: bytes | None = None) -> dict[int, Image]:
    """Parse and check ``images.bin``; a 2D point without 3D point gets id -1."""
    reader = _Reader(path, data)
    count = reader.count(_IMAGE_HEAD.size + 2 + _U64.size, "images")
    images: dict[int, Image] = {}
    names: set[str] = set()
    for _ in range(count):
        image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = reader.unpack(_IMAGE_HEAD, "an image record")
        if image_id == INVALID_ID_32 or image_id in images:
            raise _fail(path, f"image id {image_id} is invalid or appears twice")
        name = reader.name(f"the name of image {image_id}")
        _check_unique("image name", name, names, path)
        (num_points,) = reader.unpack(_U64, f"the number of 2D points of image {image_id}")
        observations = reader.array(_OBSERVATION_DTYPE, num_points, f"the 2D points of image {image_id}")
        point3d_ids = observations["point3d_id"].astype(np.int64)  # u64 max wraps to -1 = none
        bad = (point3d_ids < 0) & (observations["point3d_id"] != INVALID_POINT3D_ID_BINARY)
        if np.any(bad):
            raise _fail(path, f"image {image_id} refers to an out-of-range 3D point id")
        image = Image(
            image_id,
            name,
            camera_id,
            np.array([qw, qx, qy, qz]),
            np.array([tx, ty, tz]),
            observations["xy"].astype(np.float64).reshape(-1, 2),
            point3d_ids,
        )
        _check_pose(image, path)
        images[image_id] = image
    reader.finish()
    return images


def read_points3d_binary(path: Path, data: bytes | None = None) -> dict[int, Point3D]:
    """Parse and check ``points3D.bin``.

    One Python pass finds where each variable-length record starts; the fields are then
    gathered and checked with numpy, which keeps million-point models fast.
    """
    reader = _Reader(path, data)
    count = reader.count(_POINT_HEAD.size, "3D points")
    data, size, head = reader.data, len(reader.data), _POINT_HEAD.size
    starts, lengths = [], []
    position = reader.pos
    unpack_length = _U64.unpack_from
    for _ in range(count):
        if position + head > size:
            reader.pos = position
            reader.need(head, "a 3D point record")
        (length,) = unpack_length(data, position + head - _U64.size)
        starts.append(position)
        lengths.append(length)
        position += head + _TRACK_DTYPE.itemsize * length
        if position > size:
            raise _fail(path, f"file is truncated: the track of the 3D point record at offset {starts[-1]} "
                              f"({length} elements) runs past the end", hint="re-export the model from COLMAP")
    reader.pos = position
    reader.finish()
    if count == 0:
        return {}
    buffer = np.frombuffer(data, dtype=np.uint8)
    start_array = np.asarray(starts, dtype=np.int64)
    length_array = np.asarray(lengths, dtype=np.int64)
    head_dtype = np.dtype([("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8")])
    heads = buffer[start_array[:, None] + np.arange(head_dtype.itemsize)].reshape(-1).view(head_dtype)
    total = int(length_array.sum())
    first_element = np.cumsum(length_array) - length_array
    element_starts = (
        np.repeat(start_array + head, length_array)
        + _TRACK_DTYPE.itemsize * (np.arange(total, dtype=np.int64) - np.repeat(first_element, length_array))
    )
    elements = buffer[element_starts[:, None] + np.arange(_TRACK_DTYPE.itemsize)].reshape(-1).view(_TRACK_DTYPE)

    ids = heads["id"]
    bad = np.flatnonzero(ids >= 2**63)
    if len(bad):
        raise _fail(path, f"3D point id {int(ids[bad[0]])} is out of range")
    unique, first_index, counts = np.unique(ids, return_index=True, return_counts=True)
    if len(unique) != count:
        raise _fail(path, f"3D point id {int(unique[np.argmax(counts > 1)])} appears twice")
    finite = np.all(np.isfinite(heads["xyz"]), axis=1) & np.isfinite(heads["error"])
    if not np.all(finite):
        raise _fail(path, f"3D point {int(ids[np.argmin(finite)])} has non-finite coordinates or error")

    image_ids = elements["image_id"].astype(np.int64)
    point2d_idxs = elements["point2d_idx"].astype(np.int64)
    xyz = heads["xyz"].astype(np.float64)
    rgb = heads["rgb"].astype(np.uint8)
    points: dict[int, Point3D] = {}
    for index, (point_id, begin, length) in enumerate(zip(ids.tolist(), first_element.tolist(), lengths)):
        points[point_id] = Point3D(
            point_id,
            xyz[index],
            rgb[index],
            float(heads["error"][index]),
            image_ids[begin : begin + length],
            point2d_idxs[begin : begin + length],
        )
    return points


# --------------------------------------------------------------------------------------
# text


def _text_lines(path: Path, data: bytes | None = None) -> list[str]:
    raw = read_bytes(path) if data is None else data
    if b"\0" in raw:
        raise _fail(path, "text model file holds NUL bytes (is it a binary file named .txt?)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as error:
        raise _fail(path, f"text model file is not valid UTF-8 (byte {error.start})") from error
    # COLMAP reads lines split on '\n' and trims them; other line breaks are content to it.
    return [line.strip(_LINE_TRIM) for line in text.split("\n")]


def _is_skipped(line: str) -> bool:
    return not line or line.startswith("#")


def _split(line: str, path: Path, line_number: int) -> list[str]:
    tokens = line.split(" ")
    if "" in tokens:
        raise _fail(path, f"line {line_number}: fields must be separated by single spaces")
    return tokens


def _int(token: str, path: Path, line_number: int, what: str, low: int, high: int) -> int:
    if not _INT_RE.fullmatch(token):
        raise _fail(path, f"line {line_number}: {what} {token!r} is not an integer")
    value = int(token)
    if not low <= value <= high:
        raise _fail(path, f"line {line_number}: {what} {value} is out of range [{low}, {high}]")
    return value


def _floats(tokens: list[str], path: Path, line_number: int, what: str) -> np.ndarray:
    for token in tokens:
        if not _FLOAT_RE.fullmatch(token):
            raise _fail(path, f"line {line_number}: {what} {token!r} is not a number")
    values = np.array([float(token) for token in tokens], dtype=np.float64)
    if not np.all(np.isfinite(values)) or np.any((values != 0) & (np.abs(values) < 1e-300)):
        raise _fail(path, f"line {line_number}: {what} out of the double range")
    return values


def read_cameras_text(path: Path, data: bytes | None = None) -> dict[int, Camera]:
    """Parse and check ``cameras.txt`` (``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``)."""
    cameras: dict[int, Camera] = {}
    for number, line in enumerate(_text_lines(path, data), start=1):
        if _is_skipped(line):
            continue
        tokens = _split(line, path, number)
        if len(tokens) < 4:
            raise _fail(path, f"line {number}: a camera needs CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        camera_id = _int(tokens[0], path, number, "camera id", 0, 2**31 - 1)
        info = CAMERA_MODELS.get(tokens[1])
        if info is None:
            raise _fail(path, f"line {number}: unknown camera model {tokens[1]!r}", hint=f"known: {', '.join(CAMERA_MODELS)}")
        width = _int(tokens[2], path, number, "width", 1, MAX_IMAGE_SIDE)
        height = _int(tokens[3], path, number, "height", 1, MAX_IMAGE_SIDE)
        if len(tokens) - 4 != info.num_params:
            raise _fail(path, f"line {number}: model {info.name} takes {info.num_params} parameters, got {len(tokens) - 4}")
        if camera_id in cameras:
            raise _fail(path, f"line {number}: camera id {camera_id} appears twice")
        camera = Camera(camera_id, info.name, width, height, _floats(tokens[4:], path, number, "camera parameter"))
        _check_camera(camera, path)
        cameras[camera_id] = camera
    return cameras


def read_images_text(path: Path, data: bytes | None = None) -> dict[int, Image]:
    """Parse and check ``images.txt``: a pose line, then a (possibly empty) 2D-point line."""
    lines = _text_lines(path, data)
    images: dict[int, Image] = {}
    names: set[str] = set()
    index = 0
    while index < len(lines):
        line, number = lines[index], index + 1
        index += 1
        if _is_skipped(line):
            continue
        tokens = _split(line, path, number)
        if len(tokens) != 10:
            raise _fail(path, f"line {number}: an image needs IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (10 fields, got {len(tokens)})")
        image_id = _int(tokens[0], path, number, "image id", 0, 2**31 - 1)
        pose = _floats(tokens[1:8], path, number, "pose value")
        camera_id = _int(tokens[8], path, number, "camera id", 0, 2**31 - 1)
        name = _check_name(tokens[9].encode("utf-8"), path, f"line {number}: image name")
        if image_id in images:
            raise _fail(path, f"line {number}: image id {image_id} appears twice")
        _check_unique("image name", name, names, path)
        # The observation line always follows its pose line, even when empty.
        observation_line = lines[index] if index < len(lines) else ""
        index += 1
        if not _OBSERVATIONS_RE.fullmatch(observation_line):
            raise _fail(path, f"line {number + 1}: 2D points of image {image_id} must be X Y POINT3D_ID triples")
        tokens = observation_line.split(" ") if observation_line else []
        xy = _floats([token for i, token in enumerate(tokens) if i % 3 != 2], path, number + 1, "2D point")
        ids = [int(token) for token in tokens[2::3]]
        if any(not -1 <= value < 2**63 for value in ids):
            raise _fail(path, f"line {number + 1}: a 3D point id of image {image_id} is out of range")
        image = Image(image_id, name, camera_id, pose[:4], pose[4:], xy.reshape(-1, 2), np.array(ids, dtype=np.int64))
        _check_pose(image, path)
        images[image_id] = image
    return images


_POINT_LINE_RE = re.compile(
    rf"({_INT}) ({_FLOAT}) ({_FLOAT}) ({_FLOAT}) ({_INT}) ({_INT}) ({_INT}) ({_FLOAT})((?: {_INT} {_INT})*+)"
)


def read_points3d_text(path: Path, data: bytes | None = None) -> dict[int, Point3D]:
    """Parse and check ``points3D.txt`` (``ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)``).

    Well-formed lines take one regular-expression match; a line that does not match is
    re-read field by field to say exactly what is wrong with it.
    """
    points: dict[int, Point3D] = {}
    for number, line in enumerate(_text_lines(path, data), start=1):
        if _is_skipped(line):
            continue
        match = _POINT_LINE_RE.fullmatch(line)
        if match is None:
            _explain_point_line(line, path, number)
            raise _fail(path, f"line {number}: malformed 3D point line")
        fields = match.groups()
        point_id = int(fields[0])
        values = [float(fields[1]), float(fields[2]), float(fields[3]), float(fields[7])]
        rgb = [int(fields[4]), int(fields[5]), int(fields[6])]
        track = [int(token) for token in fields[8].split()] if fields[8] else []
        if not (
            0 <= point_id <= 2**63 - 2
            and all(0 <= value <= 255 for value in rgb)
            and all(0 <= value < 2**31 - 1 for value in track)
            and all(_double_in_range(value) for value in values)
        ):
            _explain_point_line(line, path, number)
            raise _fail(path, f"line {number}: a field of 3D point {point_id} is out of range")
        if point_id in points:
            raise _fail(path, f"line {number}: 3D point id {point_id} appears twice")
        points[point_id] = Point3D(
            point_id,
            np.array(values[:3]),
            np.array(rgb, np.uint8),
            values[3],
            np.array(track[0::2], dtype=np.int64),
            np.array(track[1::2], dtype=np.int64),
        )
    return points


def _double_in_range(value: float) -> bool:
    """Finite and representable by std::stod (which rejects subnormal results)."""
    return math.isfinite(value) and (value == 0.0 or abs(value) >= 1e-300)


def _explain_point_line(line: str, path: Path, number: int) -> None:
    """Raise the precise DatasetError for a points3D.txt line that failed the fast path."""
    tokens = line.split(" ", 8)
    if "" in tokens[:8]:
        raise _fail(path, f"line {number}: fields must be separated by single spaces")
    if len(tokens) < 8:
        raise _fail(path, f"line {number}: a 3D point needs POINT3D_ID X Y Z R G B ERROR TRACK[]")
    point_id = _int(tokens[0], path, number, "3D point id", 0, 2**63 - 2)
    _floats(tokens[1:4] + tokens[7:8], path, number, "3D point value")
    for token in tokens[4:7]:
        _int(token, path, number, "colour", 0, 255)
    track_text = tokens[8] if len(tokens) > 8 else ""
    if not _TRACK_RE.fullmatch(track_text):
        raise _fail(path, f"line {number}: the track of 3D point {point_id} must be IMAGE_ID POINT2D_IDX pairs")
    if any(not 0 <= int(token) < 2**31 - 1 for token in track_text.split(" ") if token):
        raise _fail(path, f"line {number}: the track of 3D point {point_id} holds an out-of-range id")
