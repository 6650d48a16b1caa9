"""Read and write Gaussians in the standard 3D Gaussian Splatting PLY layout.

The layout is the one the original 3DGS code writes and every splat viewer reads
(SuperSplat, gsplat's and nerfstudio's exporters, Blender splat add-ons): a single
``element vertex N`` whose float properties are, in this order,

``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1} opacity
scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3``

with ``K = (sh_degree + 1)^2`` spherical-harmonic coefficients per colour channel.
Values are stored *un-activated*: opacity as a logit, scales as natural logarithms,
the rotation as a (w, x, y, z) quaternion that is not necessarily normalised.

``f_rest`` is channel-major: first the K-1 higher-order coefficients of red, then of
green, then of blue, i.e. ``f_rest_{c*(K-1)+k} = sh_rest[n, k, c]``. (3DGS keeps the
coefficients as ``[N, K-1, 3]`` and writes ``transpose(1, 2).flatten``.)

The reader looks properties up by name, so files from tools that order the
properties differently, store doubles, omit the normals, or add properties of their
own (ignored) are accepted. docs/metrics.md describes the format in full.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ESGSError, FormatError
from ..io_utils import atomic_path

__all__ = ["GaussianPly", "write_gaussians_ply", "read_gaussians_ply", "sh_rest_property_names"]

# PLY scalar type names (both the classic and the sized spellings) -> numpy type codes.
_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}
# A header longer than this is certainly not a Gaussian PLY (3DGS headers are ~2 KB).
_MAX_HEADER_BYTES = 1 << 20
_F_REST = re.compile(r"^f_rest_(\d+)$")


@dataclass
class GaussianPly:
    """Gaussians as stored in a 3DGS PLY (raw, un-activated parameters, float32).

    means: [N, 3] centres. normals: [N, 3] (3DGS writes zeros; kept for round trips).
    sh_dc: [N, 3] degree-0 SH coefficient per colour channel.
    sh_rest: [N, K-1, 3] higher-order SH coefficients, K = (sh_degree + 1)^2 (K-1 may be 0).
    opacity_logit: [N] opacity before the sigmoid. log_scales: [N, 3] natural log of the
    axis scales. quats_wxyz: [N, 4] rotation quaternions (w, x, y, z), not normalised.
    Arrays (or torch tensors, detached and moved to the CPU) are converted to contiguous
    float32 numpy arrays on construction; shapes are checked (ESGSError when inconsistent).
    """

    means: np.ndarray
    normals: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray
    opacity_logit: np.ndarray
    log_scales: np.ndarray
    quats_wxyz: np.ndarray

    def __post_init__(self) -> None:
        for name in ("means", "normals", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats_wxyz"):
            value = getattr(self, name)
            if hasattr(value, "detach"):  # a torch tensor (possibly on a GPU, possibly with grad)
                value = value.detach().cpu().numpy()
            setattr(self, name, np.ascontiguousarray(np.asarray(value), dtype=np.float32))
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        expected = {
            "means": (n, 3), "normals": (n, 3), "sh_dc": (n, 3), "opacity_logit": (n,),
            "log_scales": (n, 3), "quats_wxyz": (n, 4),
        }
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise ESGSError(f"GaussianPly.{name} must have shape {shape}, got {getattr(self, name).shape}")
        rest = self.sh_rest
        if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3 or not _is_square(rest.shape[1] + 1):
            raise ESGSError(
                f"GaussianPly.sh_rest must have shape ({n}, K-1, 3) with K = (degree+1)^2, got {rest.shape}"
            )

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        """Spherical-harmonic degree: 0 when sh_rest is empty, 3 for 15 rest coefficients."""
        return math.isqrt(self.sh_rest.shape[1] + 1) - 1

    def opacities(self) -> np.ndarray:
        """Activated opacities in (0, 1): sigmoid of the logits. Shape [N]."""
        # exp of a large positive value overflows to inf, giving exactly 0, as the limit should
        with np.errstate(over="ignore"):
            return (1.0 / (1.0 + np.exp(-self.opacity_logit))).astype(np.float32)

    def scales(self) -> np.ndarray:
        """Activated axis scales (exp of the stored logs). Shape [N, 3]."""
        return np.exp(self.log_scales).astype(np.float32)

    def rotations_normalised(self) -> np.ndarray:
        """Unit quaternions (w, x, y, z). Shape [N, 4]; a zero quaternion becomes identity."""
        norm = np.linalg.norm(self.quats_wxyz, axis=1, keepdims=True)
        out = np.where(norm > 0, self.quats_wxyz / np.where(norm > 0, norm, 1.0), 0.0).astype(np.float32)
        out[norm[:, 0] == 0, 0] = 1.0
        return out


def _is_square(value: int) -> bool:
    return value >= 1 and math.isqrt(value) ** 2 == value


def sh_rest_property_names(num_rest: int) -> list[str]:
    """Names ``f_rest_0 .. f_rest_{3*num_rest-1}`` for ``num_rest`` = K-1 coefficients per channel."""
    return [f"f_rest_{i}" for i in range(3 * num_rest)]


def _property_names(num_rest: int) -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + sh_rest_property_names(num_rest)
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def write_gaussians_ply(path: str | Path, gaussians: GaussianPly, *, rows_per_write: int = 65_536) -> None:
    """Write ``gaussians`` as a standard 3DGS PLY (binary_little_endian 1.0), atomically.

    ``rows_per_write``: Gaussians converted and written at a time (memory, not the file, depends on it).

    All properties are float32 in the canonical 3DGS order (see the module docstring),
    ``f_rest`` channel-major. The file appears at ``path`` only once it is complete.
    """
    path = Path(path)
    if int(rows_per_write) < 1:
        raise ValueError(f"rows_per_write must be at least 1, got {rows_per_write}")
    n = len(gaussians)
    num_rest = gaussians.sh_rest.shape[1]
    names = _property_names(num_rest)
    header = "ply\nformat binary_little_endian 1.0\n"
    header += "comment written by ESGS for Blender (3DGS layout, f_rest channel-major)\n"
    header += f"element vertex {n}\n"
    header += "".join(f"property float {name}\n" for name in names)
    header += "end_header\n"
    columns = [gaussians.means, gaussians.normals, gaussians.sh_dc, None, gaussians.opacity_logit[:, None],
               gaussians.log_scales, gaussians.quats_wxyz]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:
            handle.write(header.encode("ascii"))
            # the table a block of rows at a time: a whole [N, 62] table and its bytes were two
            # copies of the model at the end of every run (~0.5 KB a Gaussian, the run's peak)
            for start in range(0, n, rows_per_write):
                rows = slice(start, start + rows_per_write)
                # sh_rest [N, K-1, 3] -> [N, 3, K-1]: all red coefficients first, then green, then blue
                rest = np.transpose(gaussians.sh_rest[rows], (0, 2, 1)).reshape(min(rows_per_write, n - start),
                                                                                3 * num_rest)
                block = np.concatenate([rest if column is None else column[rows] for column in columns],
                                       axis=1).astype("<f4", copy=False)
                assert block.shape[1] == len(names)
                handle.write(np.ascontiguousarray(block).data)
            handle.flush()
            os.fsync(handle.fileno())


@dataclass
class _Element:
    name: str
    count: int
    properties: list[tuple[str, str]]  # (name, numpy type code); list properties -> "list"


def _read_header(handle, path: Path) -> tuple[str | None, list[_Element], int]:
    """Parse the header; returns (byte-order char or None for ascii, elements, data offset)."""
    first = handle.readline(16)
    if first.rstrip(b"\r\n") != b"ply":
        raise FormatError("not a PLY file (it does not start with 'ply')", path=path)
    fmt: str | None = "missing"
    elements: list[_Element] = []
    total = len(first)
    while True:
        raw = handle.readline(_MAX_HEADER_BYTES)
        total += len(raw)
        if not raw.endswith(b"\n") or total > _MAX_HEADER_BYTES:
            raise FormatError("PLY header has no 'end_header' line", path=path, hint="the file is truncated or not a PLY")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise FormatError("PLY header contains non-ASCII bytes", path=path) from None
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise FormatError(f"unsupported PLY format line '{line}'", path=path)
            fmt = _FORMATS[words[1]]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise FormatError(f"malformed PLY element line '{line}'", path=path)
            elements.append(_Element(words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise FormatError(f"PLY property before any element: '{line}'", path=path)
            if len(words) == 5 and words[1] == "list":
                elements[-1].properties.append((words[4], "list"))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1].properties.append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise FormatError(f"malformed PLY property line '{line}'", path=path)
        else:
            raise FormatError(f"unknown PLY header line '{line}'", path=path)
    if fmt == "missing":
        raise FormatError("PLY header has no 'format' line", path=path)
    return fmt, elements, total


def read_gaussians_ply(path: str | Path) -> GaussianPly:
    """Read a standard 3DGS PLY (any property order, float or double, extra properties ignored).

    Returns float32 arrays (see :class:`GaussianPly`). Raises :class:`FormatError` naming the
    file when it is not a PLY, has no Gaussian properties (a mesh or plain point cloud), has an
    SH coefficient count that is not 3((d+1)^2 - 1), or is shorter than its header says.
    """
    path = Path(path)
    try:
        handle = open(path, "rb")
    except OSError as err:
        raise FormatError(f"cannot open PLY file: {err.strerror}", path=path) from None
    with handle:
        byte_order, elements, data_offset = _read_header(handle, path)
        vertex_index = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
        if vertex_index is None:
            raise FormatError("PLY has no 'vertex' element, so it holds no Gaussians", path=path)
        vertex = elements[vertex_index]
        names = [name for name, _ in vertex.properties]
        columns = _gaussian_columns(names, path)
        if any(kind == "list" for _, kind in vertex.properties):
            raise FormatError("the PLY vertex element has list properties; not a 3DGS PLY", path=path)
        if byte_order is None:
            table = _read_ascii_vertices(handle, elements, vertex_index, path)
        else:
            offset = data_offset + _bytes_before(elements, vertex_index, byte_order, path)
            table = _read_binary_vertices(handle, path, vertex, byte_order, offset)
    return _gaussians_from_table(table, names, columns)


def _gaussian_columns(names: list[str], path: Path) -> dict[str, list[int]]:
    """Column index of every Gaussian property, by name; FormatError if any is missing."""
    index = {name: i for i, name in enumerate(names)}
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [name for name in required if name not in index]
    if missing:
        raise FormatError(
            f"not a 3D Gaussian Splatting PLY: vertex properties {', '.join(missing)} are missing",
            path=path,
            hint="expected the 3DGS layout x y z [nx ny nz] f_dc_* f_rest_* opacity scale_* rot_*",
        )
    rest_ids = sorted(int(m.group(1)) for name in names if (m := _F_REST.match(name)))
    if rest_ids != list(range(len(rest_ids))) or len(rest_ids) % 3 or not _is_square(len(rest_ids) // 3 + 1):
        raise FormatError(
            f"PLY has {len(rest_ids)} f_rest_* properties; expected f_rest_0..f_rest_{{3((d+1)^2-1)-1}} "
            "(0, 9, 24 or 45 for SH degree 0..3)",
            path=path,
        )
    columns = {name: [index[name]] for name in required}
    columns["normals"] = [index[n] for n in ("nx", "ny", "nz")] if all(n in index for n in ("nx", "ny", "nz")) else []
    columns["f_rest"] = [index[f"f_rest_{i}"] for i in range(len(rest_ids))]
    return columns


def _bytes_before(elements: list[_Element], stop: int, byte_order: str, path: Path) -> int:
    """Size of the binary data of the elements stored before element ``stop``."""
    size = 0
    for element in elements[:stop]:
        if any(kind == "list" for _, kind in element.properties):
            raise FormatError(
                f"element '{element.name}' with list properties precedes the vertices; not a 3DGS PLY", path=path
            )
        size += element.count * sum(np.dtype(byte_order + kind).itemsize for _, kind in element.properties)
    return size


def _read_binary_vertices(handle, path: Path, vertex: _Element, byte_order: str, offset: int) -> np.ndarray:
    """The vertex block as an [N, P] array (native float32/float64) or a structured array."""
    kinds = {kind for _, kind in vertex.properties}
    if len(kinds) == 1:
        item = np.dtype(byte_order + kinds.pop())
        row_bytes = item.itemsize * len(vertex.properties)
    else:
        item = np.dtype([(f"p{i}", byte_order + kind) for i, (_, kind) in enumerate(vertex.properties)])
        row_bytes = item.itemsize
    needed = offset + row_bytes * vertex.count
    size = os.fstat(handle.fileno()).st_size
    if size < needed:
        raise FormatError(
            f"PLY file is truncated: its header announces {vertex.count} vertices "
            f"({needed} bytes) but the file has {size} bytes",
            path=path,
            hint="the file was cut short while writing or copying; write or copy it again",
        )
    handle.seek(offset)
    count = vertex.count * (len(vertex.properties) if item.names is None else 1)
    data = np.fromfile(handle, dtype=item, count=count)
    if data.size != count:
        raise FormatError("PLY file is truncated (fewer vertex bytes than the header announces)", path=path)
    if item.names is None:
        return data.reshape(vertex.count, len(vertex.properties))
    return data


def _read_ascii_vertices(handle, elements: list[_Element], vertex_index: int, path: Path) -> np.ndarray:
    """ASCII PLY: skip the lines of earlier elements, parse the vertex lines as numbers."""
    vertex = elements[vertex_index]
    skip = sum(element.count for element in elements[:vertex_index])
    for _ in range(skip):
        if not handle.readline():
            raise FormatError("PLY file is truncated (ASCII data ends early)", path=path)
    lines = [handle.readline() for _ in range(vertex.count)]
    if vertex.count and not lines[-1]:
        raise FormatError(f"PLY file is truncated: fewer than {vertex.count} vertex lines", path=path)
    try:
        table = np.array(b" ".join(lines).split(), dtype=np.float64)
    except ValueError:
        raise FormatError("PLY ASCII vertex data contains a non-number", path=path) from None
    if table.size != vertex.count * len(vertex.properties):
        raise FormatError(
            f"PLY ASCII vertex data has {table.size} numbers, expected {vertex.count} x {len(vertex.properties)}",
            path=path,
        )
    return table.reshape(vertex.count, len(vertex.properties))


def _gaussians_from_table(table: np.ndarray, names: list[str], columns: dict[str, list[int]]) -> GaussianPly:
    if table.dtype.names is None:
        def take(ids: list[int]) -> np.ndarray:
            return table[:, ids].astype(np.float32) if ids else np.zeros((table.shape[0], 0), np.float32)
    else:
        fields = table.dtype.names

        def take(ids: list[int]) -> np.ndarray:
            out = np.empty((table.shape[0], len(ids)), np.float32)
            for j, i in enumerate(ids):
                out[:, j] = table[fields[i]]
            return out

    n = table.shape[0]
    rest = take(columns["f_rest"])
    num_rest = rest.shape[1] // 3
    return GaussianPly(
        means=take(columns["x"] + columns["y"] + columns["z"]),
        normals=take(columns["normals"]) if columns["normals"] else np.zeros((n, 3), np.float32),
        sh_dc=take(columns["f_dc_0"] + columns["f_dc_1"] + columns["f_dc_2"]),
        # channel-major on disk: [N, 3, K-1] -> [N, K-1, 3]
        sh_rest=rest.reshape(n, 3, num_rest).transpose(0, 2, 1),
        opacity_logit=take(columns["opacity"])[:, 0],
        log_scales=take(columns["scale_0"] + columns["scale_1"] + columns["scale_2"]),
        quats_wxyz=take(columns["rot_0"] + columns["rot_1"] + columns["rot_2"] + columns["rot_3"]),
    )
