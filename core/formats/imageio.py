"""Image and EXR files: reading with clear errors, writing atomically.

- 8-bit images (PNG, JPEG...) go through OpenCV; arrays are RGB (OpenCV's BGR is
  converted at the boundary), ``[H, W, 3]`` uint8 or ``[H, W]`` uint8 for grey images.
- EXR files go through the OpenEXR 3.5 Python API (``OpenEXR.File``): named float32
  channels ``[H, W]`` plus string metadata in the header. Depth maps are one channel
  ``Z`` (distance along the camera z axis), normal maps three channels ``X``, ``Y``, ``Z``;
  the header states the frame and units (``frame="camera_opencv"``, ``units="m"``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from ..errors import DatasetError, ESGSError, FormatError
from ..io_utils import atomic_path, atomic_write_bytes

#: Larger than any map this project writes; beyond it a header is taken as corrupt.
MAX_EXR_SIDE = 65536
#: Header attributes OpenEXR manages itself; user metadata may not use these names.
_EXR_STANDARD_ATTRIBUTES = frozenset(
    {
        "channels",
        "compression",
        "dataWindow",
        "displayWindow",
        "lineOrder",
        "pixelAspectRatio",
        "screenWindowCenter",
        "screenWindowWidth",
        "tiles",
        "type",
        "name",
        "version",
        "chunkCount",
        "view",
    }
)


# --------------------------------------------------------------------------------------
# 8-bit images


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file: ``[H, W, 3]`` uint8 RGB, or ``[H, W]`` uint8 for grey images.

    16-bit images are scaled to 8 bits; an alpha channel is dropped. Unreadable,
    missing or empty files raise :class:`DatasetError` naming the file.
    """
    import cv2

    path = Path(path)
    try:
        # imdecode on the bytes (not imread) so non-ASCII paths work on every platform.
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as error:
        raise DatasetError(f"cannot read image: {error.strerror or error}", path=path) from error
    if data.size == 0:
        raise DatasetError("image file is empty", path=path)
    array = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if array is None or array.size == 0:
        raise DatasetError("cannot decode image (corrupt or unsupported format)", path=path, hint="re-export it as PNG or JPEG")
    if array.dtype == np.uint16:
        array = np.round(array.astype(np.float32) / 257.0).astype(np.uint8)
    elif array.dtype != np.uint8:
        raise DatasetError(f"unsupported image sample type {array.dtype}", path=path, hint="use 8- or 16-bit images")
    if array.ndim == 3:
        if array.shape[2] == 1:
            return np.ascontiguousarray(array[:, :, 0])
        if array.shape[2] == 4:
            array = array[:, :, :3]
        array = cv2.cvtColor(array, cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(array)


def write_png(path: str | Path, array: np.ndarray) -> Path:
    """Write ``array`` as a PNG atomically and return ``path``.

    ``array``: ``[H, W]`` grey, ``[H, W, 3]`` RGB or ``[H, W, 4]`` RGBA, uint8 or uint16.
    """
    import cv2

    path = Path(path)
    array = np.asarray(array)
    if array.dtype not in (np.uint8, np.uint16):
        raise FormatError(f"PNG needs uint8 or uint16 samples, got {array.dtype}", path=path)
    if array.ndim == 3 and array.shape[2] == 3:
        array = cv2.cvtColor(np.ascontiguousarray(array), cv2.COLOR_RGB2BGR)
    elif array.ndim == 3 and array.shape[2] == 4:
        array = cv2.cvtColor(np.ascontiguousarray(array), cv2.COLOR_RGBA2BGRA)
    elif array.ndim != 2:
        raise FormatError(f"PNG needs [H, W], [H, W, 3] or [H, W, 4], got shape {array.shape}", path=path)
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise FormatError(f"cannot write an empty image (shape {array.shape})", path=path)
    ok, encoded = cv2.imencode(".png", array)
    if not ok:
        raise FormatError("OpenCV could not encode the PNG", path=path)
    atomic_write_bytes(path, encoded.tobytes())
    return path


# --------------------------------------------------------------------------------------
# EXR


def write_exr(
    path: str | Path,
    channels: Mapping[str, np.ndarray],
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Write named float32 channels (each ``[H, W]``, same size) and string metadata to an EXR.

    ZIP-compressed (lossless) scanline file, written atomically; returns ``path``.
    """
    import OpenEXR

    path = Path(path)
    if not channels:
        raise FormatError("an EXR needs at least one channel", path=path)
    arrays: dict[str, np.ndarray] = {}
    shape = None
    for name, values in channels.items():
        array = np.asarray(values)
        if array.ndim != 2 or array.size == 0:
            raise FormatError(f"EXR channel {name!r} must be a non-empty [H, W] array, got shape {array.shape}", path=path)
        if shape is not None and array.shape != shape:
            raise FormatError(f"EXR channel {name!r} is {array.shape}, other channels are {shape}", path=path)
        shape = array.shape
        arrays[str(name)] = np.ascontiguousarray(array, dtype=np.float32)
    header: dict[str, object] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (metadata or {}).items():
        if key in _EXR_STANDARD_ATTRIBUTES or not isinstance(key, str) or not key:
            raise ESGSError(f"EXR metadata key {key!r} is reserved or invalid", path=path)
        if not isinstance(value, str):
            raise ESGSError(f"EXR metadata {key!r} must be a string, got {type(value).__name__}", path=path)
        header[key] = value
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(header, arrays).write(str(tmp))
        except Exception as error:  # OpenEXR raises plain RuntimeError/TypeError
            raise FormatError(f"OpenEXR could not write the file: {error}", path=path) from error
    return path


def read_exr(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Read an EXR: (channels ``{name: [H, W] float32}``, string metadata ``{key: value}``).

    Half-float channels are widened to float32 (exactly); uint32 channels are kept.
    A missing, truncated or corrupt file raises :class:`DatasetError`.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise DatasetError("EXR file does not exist", path=path)
    try:
        # The header first: a corrupt data window must not make OpenEXR allocate gigabytes.
        header = OpenEXR.File(str(path), header_only=True).header()
        low, high = (np.asarray(corner, dtype=np.int64) for corner in header["dataWindow"])
        width, height = (high - low + 1).tolist()
        num_channels = len(header["channels"])
        if not (0 < width <= MAX_EXR_SIDE and 0 < height <= MAX_EXR_SIDE and 0 < num_channels <= 64):
            raise DatasetError(f"EXR header announces an implausible {width} x {height} x {num_channels} image", path=path)
        # OpenEXR drops a part whose pixels fail to decode (printing a warning), so a
        # damaged file surfaces here as an exception from channels().
        exr = OpenEXR.File(str(path), separate_channels=True)
        header = exr.header()
        channels = {}
        for name, channel in exr.channels().items():
            pixels = np.asarray(channel.pixels)
            if pixels.shape != (height, width):
                raise DatasetError(f"EXR channel {name!r} is {pixels.shape}, the header says {(height, width)}", path=path)
            if pixels.dtype == np.float16:
                pixels = pixels.astype(np.float32)
            channels[str(name)] = np.ascontiguousarray(pixels)
    except DatasetError:
        raise
    except Exception as error:  # OpenEXR raises RuntimeError/ValueError/KeyError on damaged files
        raise DatasetError(f"cannot read EXR (truncated or corrupt): {error}", path=path, hint="re-create the file") from error
    metadata = {str(key): value for key, value in header.items() if isinstance(value, str) and key not in _EXR_STANDARD_ATTRIBUTES}
    return channels, metadata


def write_depth_exr(
    path: str | Path,
    depth: np.ndarray,
    *,
    units: str = "m",
    frame: str = "camera_opencv",
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Write a depth map ``[H, W]`` (distance along the camera z axis; 0 = invalid) as channel ``Z``.

    The header records ``units``, ``frame`` and ``quantity="depth_z"`` plus any extra ``metadata``.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise FormatError(f"a depth map must be [H, W], got shape {depth.shape}", path=path)
    header = {"quantity": "depth_z", "units": units, "frame": frame}
    header.update(metadata or {})
    return write_exr(path, {"Z": depth}, header)


def read_depth_exr(path: str | Path) -> tuple[np.ndarray, dict[str, str]]:
    """Read a depth map: (``[H, W]`` float32, metadata).

    Takes channel ``Z``, or the only channel of a one-channel file (Blender writes ``V``).
    """
    channels, metadata = read_exr(path)
    if "Z" in channels:
        return channels["Z"], metadata
    if len(channels) == 1:
        return next(iter(channels.values())), metadata
    raise DatasetError(
        f"EXR has no depth channel 'Z' (channels: {', '.join(sorted(channels))})", path=path, hint="write depth with write_depth_exr"
    )


def write_normal_exr(
    path: str | Path,
    normals: np.ndarray,
    *,
    frame: str = "camera_opencv",
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Write unit normals ``[H, W, 3]`` as channels ``X``, ``Y``, ``Z``; the header records ``frame``."""
    normals = np.asarray(normals)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise FormatError(f"a normal map must be [H, W, 3], got shape {normals.shape}", path=path)
    header = {"quantity": "normal", "frame": frame}
    header.update(metadata or {})
    return write_exr(path, {"X": normals[:, :, 0], "Y": normals[:, :, 1], "Z": normals[:, :, 2]}, header)


def read_normal_exr(path: str | Path) -> tuple[np.ndarray, dict[str, str]]:
    """Read a normal map: (``[H, W, 3]`` float32 from channels X, Y, Z; metadata)."""
    channels, metadata = read_exr(path)
    if not {"X", "Y", "Z"} <= set(channels):
        for names in (("R", "G", "B"),):  # some tools store normals as colour channels
            if set(names) <= set(channels):
                return np.stack([channels[name] for name in names], axis=-1), metadata
        raise DatasetError(
            f"EXR has no normal channels X, Y, Z (channels: {', '.join(sorted(channels))})",
            path=path,
            hint="write normals with write_normal_exr",
        )
    return np.stack([channels["X"], channels["Y"], channels["Z"]], axis=-1), metadata
