"""The run-folder files the 3DGS reference code writes, so its viewers and tools open our runs.

Beside ``RUN/point_cloud.ply`` (already the 3DGS PLY layout, :mod:`esgs.core.formats.ply`) a
finished run gets, as ``train.py`` of graphdeco-inria/gaussian-splatting leaves them:

- ``point_cloud/iteration_<N>/point_cloud.ply``: the same file (a hard link where the file
  system allows, else a copy), N = the run's last step;
- ``cameras.json``: a list with one object per image (ids 0.., images sorted by name, train
  and held-out views alike): ``id``, ``img_name`` (the image name without its extension),
  ``width``, ``height`` (pixels, at the training resolution), ``position`` (the camera
  centre in world coordinates), ``rotation`` (the 3x3 camera-to-world rotation, rows as
  nested lists, OpenCV camera axes: x right, y down, z forward), ``fx``, ``fy`` (pixels);
- ``cfg_args``: the ``argparse.Namespace`` repr the reference writes (SIBR's viewer reads
  ``source_path`` and ``white_background`` from it).

Every file appears atomically.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path, PurePosixPath
from typing import Any, Iterable, Sequence

import numpy as np

from ..io_utils import atomic_path, atomic_write_json, atomic_write_text
from .run_dir import RunDir

__all__ = ["camera_entry", "write_reference_layout", "cfg_args_text", "link_or_copy"]


def camera_entry(index: int, name: str, width: int, height: int, K: Any, viewmat: Any) -> dict:
    """One ``cameras.json`` object. K: [3, 3] intrinsics; viewmat: [4, 4] world-to-camera (OpenCV axes)."""
    K = np.asarray(_numpy(K), dtype=np.float64)
    viewmat = np.asarray(_numpy(viewmat), dtype=np.float64)
    rotation_w2c, translation = viewmat[:3, :3], viewmat[:3, 3]
    camera_to_world = rotation_w2c.T
    position = -camera_to_world @ translation
    return {
        "id": int(index),
        "img_name": str(PurePosixPath(str(name).replace(os.sep, "/")).with_suffix("")),
        "width": int(width),
        "height": int(height),
        "position": [float(v) for v in position],
        "rotation": [[float(v) for v in row] for row in camera_to_world],
        "fy": float(K[1, 1]),
        "fx": float(K[0, 0]),
    }


def cfg_args_text(*, sh_degree: int, source_path: str | Path, model_path: str | Path, images: str = "images",
                  resolution: int = -1, white_background: bool = False, eval: bool = True) -> str:
    """The reference's ``cfg_args``: ``repr`` of its ``argparse.Namespace`` of model parameters."""
    values = {
        "sh_degree": int(sh_degree), "source_path": str(Path(source_path).resolve()),
        "model_path": str(Path(model_path).resolve()), "images": str(images), "depths": "",
        "resolution": int(resolution), "white_background": bool(white_background), "train_test_exp": False,
        "data_device": "cuda", "eval": bool(eval),
    }
    return "Namespace(" + ", ".join(f"{key}={value!r}" for key, value in values.items()) + ")"


def link_or_copy(source: str | Path, target: str | Path) -> None:
    """Make ``target`` a hard link to ``source`` (a copy where links are refused), atomically."""
    with atomic_path(target) as tmp:
        tmp.unlink()
        try:
            os.link(source, tmp)
        except OSError:
            shutil.copyfile(source, tmp)


def write_reference_layout(run: RunDir, step: int, views: Iterable[Any], *, cfg_args: str | None = None) -> None:
    """Write ``point_cloud/iteration_<step>/point_cloud.ply`` (from ``run.point_cloud``, which must
    exist), ``cameras.json`` from ``views`` (objects with ``index``, ``name``, ``width``, ``height``,
    ``K``, ``viewmat`` as :class:`esgs.core.train.dataset.View`) and ``cfg_args`` when given.

    Other ``iteration_*`` folders (from before a resumed run went on) are removed: the folder
    holds the model of ``point_cloud.ply`` only, and viewers open the highest iteration.
    """
    target = run.point_cloud_iteration(step)
    link_or_copy(run.point_cloud, target)
    for folder in run.point_cloud_iterations.glob("iteration_*"):
        if folder.is_dir() and folder != target.parent:
            shutil.rmtree(folder, ignore_errors=True)
    ordered: Sequence[Any] = sorted(views, key=lambda view: (view.name, view.index))
    entries = [camera_entry(i, view.name, view.width, view.height, view.K, view.viewmat) for i, view in enumerate(ordered)]
    atomic_write_json(run.cameras_json, entries)
    if cfg_args is not None:
        atomic_write_text(run.cfg_args, cfg_args)


def _numpy(value: Any) -> Any:
    if hasattr(value, "detach"):
        return value.detach().cpu().numpy()
    return value
