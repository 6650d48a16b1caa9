"""Reading and writing the label meshes (PLY, OBJ, anything trimesh reads) as plain arrays."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DatasetError


def load_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices [V, 3] float64, triangles [F, 3] int64) of a triangle mesh file.

    Scenes (several meshes in one file) are concatenated in their world placement. Raises
    :class:`DatasetError` naming the file when it is missing, unreadable, or holds no
    triangles.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise DatasetError("mesh file not found", path=path,
                           hint="give an existing .ply/.obj/.stl file, or use --reconstruct to build one from the images")
    try:
        loaded = trimesh.load(path, process=False, force="mesh")
    except Exception as error:  # trimesh raises many kinds for bad files
        raise DatasetError(f"cannot read the mesh: {error}", path=path, hint="export it as a triangle PLY or OBJ") from error
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    triangles = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
    if len(vertices) == 0 or len(triangles) == 0 or triangles.ndim != 2 or triangles.shape[1] != 3:
        raise DatasetError("the mesh has no triangles (a point cloud?)", path=path,
                           hint="label rendering needs a surface: mesh the points first, or use --reconstruct")
    if not np.all(np.isfinite(vertices)):
        raise DatasetError("the mesh has non-finite vertex coordinates", path=path)
    return vertices, triangles


def write_mesh(path: str | Path, vertices: np.ndarray, triangles: np.ndarray,
               vertex_colors: np.ndarray | None = None) -> Path:
    """Write a binary PLY atomically. vertices: [V, 3]; triangles: [F, 3]; vertex_colors: [V, 3] uint8."""
    import trimesh

    from ..io_utils import atomic_path

    path = Path(path)
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(triangles, np.int64), process=False,
                           vertex_colors=vertex_colors)
    with atomic_path(path) as temporary:
        mesh.export(temporary, file_type="ply", encoding="binary")
    return path
