"""A scene whose sparse points come from structure from motion on its own images.

A synthetic scene's ``sparse/0`` holds exact surface points lifted from the rendered depth:
training from them (and making ``sfm`` priors from them) flatters every method, since a
real capture never has them. :func:`make_sfm_scene` keeps the scene's known camera poses
and intrinsics but replaces the points by what COLMAP makes of the images: SIFT features,
exhaustive matching with geometric verification, triangulation and point-only bundle
adjustment with the poses held fixed (``pycolmap.triangulate_points``). The new folder
gets:

- ``images/``, ``mesh/``, ``priors/gt/`` and ``scene.json`` copied from the source scene
  (``scene.json`` gains ``"sparse_points"``: how the points were made, with their count and
  mean reprojection error);
- ``sparse/0``: the known poses with the triangulated points (noisy, only where the images
  have texture, typically a few hundred per view instead of thousands);
- ``priors/sfm/``: the sparse depth priors of those points (:func:`..priors.sfm.write_sfm_priors`).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from ..colmap.triangulate import triangulate_known_poses
from ..errors import DatasetError
from ..progress import ProgressCallback, ProgressEvent, no_progress
from ..formats.scene_dir import PriorSource, SceneDir

#: Where a synthetic scene's SfM points come from: ``triangulated`` from its rendered images
#: with the known poses (:func:`make_sfm_scene`, as a real capture gives them), or ``exact``:
#: the generator's surface samples (flatter every method's geometry).
SPARSE_POINTS = ("triangulated", "exact")


def copied(scene: SceneDir) -> tuple[Path, ...]:
    """The folders of ``scene`` copied unchanged into its SfM copy (``scene.json`` is rewritten)."""
    return scene.images, scene.mesh, scene.prior(PriorSource.GT)


def triangulate_into(scene: str | Path, output: str | Path, *, max_features: int = 8192,
                     verbose: bool = False) -> dict[str, Any]:
    """Triangulate SIFT matches of ``scene/images`` with the poses of ``scene/sparse/0``
    (:func:`..colmap.triangulate.triangulate_known_poses`).

    Writes a COLMAP binary model to ``output`` (must not exist) with the same cameras and
    poses and the triangulated points; returns {"points", "observations",
    "mean_reprojection_error_px", "mean_track_length"}. Raises DatasetError when no point
    could be triangulated (images without texture or overlap).
    """
    folder, output = SceneDir(scene), Path(output)
    result = triangulate_known_poses(folder.images, folder.model, max_features=max_features, verbose=verbose)
    if result.num_points3D() == 0:
        raise DatasetError("no point could be triangulated from the images with their known poses",
                           path=folder.images, hint="the views need overlap and texture")
    output.mkdir(parents=True)
    result.write(str(output))
    return {"points": int(result.num_points3D()), "observations": int(result.compute_num_observations()),
            "mean_reprojection_error_px": float(result.compute_mean_reprojection_error()),
            "mean_track_length": float(result.compute_mean_track_length())}


def make_sfm_scene(scene: str | Path, out: str | Path, *, overwrite: bool = False,
                   progress: ProgressCallback = no_progress) -> dict[str, Any]:
    """Copy ``scene`` to ``out`` with triangulated SfM points and their ``sfm`` priors (module docstring).

    Returns the ``sparse_points`` record written into ``out/scene.json``. The folder is built
    in a temporary sibling and appears only when complete.
    """
    from ..colmap import read_model
    from ..io_utils import atomic_directory, atomic_write_json
    from ..priors.sfm import write_sfm_priors

    scene, out = Path(scene), Path(out)
    source = SceneDir(scene)
    if not source.model.is_dir() or not source.images.is_dir():
        raise DatasetError("not a scene folder (images/ and sparse/0 needed)", path=scene,
                           hint="make one with esgs scene")
    with atomic_directory(out, overwrite=overwrite) as staging:
        staged = SceneDir(staging)
        for folder in copied(source):
            if folder.is_dir():
                shutil.copytree(folder, staging / folder.relative_to(scene))
        progress(ProgressEvent(0, 2, stage="sfm scene", message="triangulating"))
        record = triangulate_into(scene, staged.model)
        record["method"] = ("pycolmap: SIFT on the rendered images, exhaustive matching, triangulation "
                            "with the known poses and intrinsics")
        record["source_scene"] = str(scene)
        model = read_model(staging)
        write_sfm_priors(staging, model)
        progress(ProgressEvent(1, 2, stage="sfm scene", message="sfm priors"))
        provenance = json.loads(source.provenance.read_text()) if source.provenance.is_file() else {}
        provenance["sparse_points"] = record
        provenance["points3d"] = record["points"]
        provenance.setdefault("priors", {})["sfm"] = ["depth", "mask"]
        atomic_write_json(staged.provenance, provenance)
    progress(ProgressEvent(2, 2, stage="sfm scene", message="done"))
    return record


def point_to_mesh_distances(points: np.ndarray, mesh_path: str | Path) -> np.ndarray:
    """[N] unsigned distances of ``points`` [N, 3] to the surface of the mesh at ``mesh_path``.

    The same exact kernel as ``esgs compare`` (:func:`..metrics.geometry.point_to_mesh_distances`),
    so the acceptance study and the comparison measure with one piece of code.
    """
    from ..metrics.geometry import load_mesh
    from ..metrics.geometry import point_to_mesh_distances as exact_distances

    vertices, faces = load_mesh(mesh_path)
    return exact_distances(np.asarray(points, np.float64), vertices, faces)
