"""Writing a scene's label maps: every view filled, written, and swapped in at once.

``SCENE/priors/labels/`` is built in a staging folder inside the scene
(``SCENE/.labels.partial.*``) and only replaces an existing ``priors/labels`` once every
view is written, so a failure (a crash in Blender, a missing pass, Ctrl-C) leaves the
previous labels, or nothing, never a mix.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DatasetError
from ..io_utils import atomic_write_json
from ..priors.io import write_prior_maps
from ..formats.scene_dir import PriorSource, SceneDir
from .fill import EMPTY, FILLED, RENDERED, FillOptions, fill_missing

SOURCE = PriorSource.LABELS
MASK_VALUES = f"{RENDERED} rendered from the mesh, {FILLED} filled (hole filling), {EMPTY} no label"


class LabelWriter:
    """Collects the rendered views of one label run and writes them atomically.

    Use as a context manager::

        with LabelWriter(scene_dir, {"mesh": "...", "method": "mesh"}) as writer:
            for name, depth, normal in rendered_views:
                writer.add(name, depth, normal)

    On a clean exit the staging folder becomes ``SCENE/priors/labels``; on an exception it
    is deleted and the scene is left as it was.
    """

    def __init__(self, scene_dir: str | Path, metadata: dict[str, Any], fill: FillOptions | None = None):
        self.scene_dir = Path(scene_dir)
        if not self.scene_dir.is_dir():
            raise DatasetError("scene folder not found", path=self.scene_dir)
        self.metadata = {key: str(value) for key, value in metadata.items()}
        self.fill = fill or FillOptions()
        self.fill.validate()
        self.views: list[dict[str, Any]] = []
        self._staging: Path | None = None

    def __enter__(self) -> "LabelWriter":
        self._staging = Path(tempfile.mkdtemp(prefix=".labels.partial.", dir=self.scene_dir))
        return self

    def add(self, image_name: str, depth: np.ndarray, normal: np.ndarray,
            exclude: np.ndarray | None = None) -> dict[str, Any]:
        """Fill and write one view. depth: [H, W] float32 along the camera z axis, 0 = no
        surface; normal: [H, W, 3] unit normals, camera frame (OpenCV axes); exclude: [H, W]
        bool, rendered pixels not to trust (seen through a gap of a reconstructed mesh,
        :mod:`.gaps`): they count as not rendered, so hole filling may fill them. Returns the
        view's statistics (also saved in ``labels.json``)."""
        if self._staging is None:
            raise RuntimeError("LabelWriter.add outside its with-block")
        depth = np.asarray(depth, np.float32)
        normal = np.asarray(normal, np.float32)
        if depth.ndim != 2 or normal.shape != (*depth.shape, 3):
            raise DatasetError(f"view {image_name!r}: depth {depth.shape} and normal {normal.shape} do not match",
                               path=self.scene_dir)
        rendered = depth > 0
        excluded = np.zeros_like(rendered)
        if exclude is not None:
            if np.shape(exclude) != depth.shape:
                raise DatasetError(f"view {image_name!r}: exclusion mask {np.shape(exclude)} does not match depth "
                                   f"{depth.shape}", path=self.scene_dir)
            excluded = rendered & np.asarray(exclude, bool)
            rendered = rendered & ~excluded
            depth = np.where(rendered, depth, 0.0).astype(np.float32)
        filled_depth, filled_normal, mask = fill_missing(depth, normal, rendered, self.fill)
        total = mask.size
        stats = {"image": image_name, "rendered_fraction": float((mask == RENDERED).sum() / total),
                 "filled_fraction": float((mask == FILLED).sum() / total),
                 "empty_fraction": float((mask == EMPTY).sum() / total),
                 "through_gap_fraction": float(excluded.sum() / total)}
        write_prior_maps(self._staging, SOURCE, image_name, depth=filled_depth, normal=filled_normal, mask=None,
                         metadata={**self.metadata, "mask_values": MASK_VALUES,
                                   "filled_pixels": str(int((mask == FILLED).sum()))})
        # the mask keeps three values (write_prior_maps would binarise it)
        from ..formats.imageio import write_png

        write_png(SceneDir(self._staging).mask_map(SOURCE, image_name), mask)
        self.views.append(stats)
        return stats

    def __exit__(self, kind, error, traceback) -> None:
        staging, self._staging = self._staging, None
        assert staging is not None
        try:
            if kind is not None:
                return
            if not self.views:
                raise DatasetError("no views were rendered; nothing written", path=self.scene_dir)
            if all(view["rendered_fraction"] == 0 for view in self.views):
                raise DatasetError("no camera sees the mesh; nothing written", path=self.metadata.get("mesh"),
                                   hint="the mesh must be in the COLMAP model's frame and units (for a synthetic "
                                        "scene: mesh/ground_truth.ply)")
            built = SceneDir(staging).prior(SOURCE)
            atomic_write_json(SceneDir(staging).labels_report, {
                "source": SOURCE.value, **self.metadata, "mask_values": MASK_VALUES,
                "fill": {"max_hole_fraction": self.fill.max_hole_fraction, "edge_radius_px": self.fill.edge_radius_px,
                         "method": "membrane (Laplace) interpolation of inverse depth and normals"},
                "views": self.views,
            })
            _replace_directory(built, SceneDir(self.scene_dir).prior(SOURCE))
        finally:
            shutil.rmtree(staging, ignore_errors=True)


def _replace_directory(built: Path, target: Path) -> None:
    """Move ``built`` to ``target``, replacing an existing ``target`` only at the very end."""
    target.parent.mkdir(parents=True, exist_ok=True)
    if not target.exists():
        os.replace(built, target)
        return
    trash = Path(tempfile.mkdtemp(prefix=f".{target.name}.old.", dir=target.parent))
    os.replace(target, trash / target.name)
    try:
        os.replace(built, target)
    except BaseException:
        os.replace(trash / target.name, target)  # put the previous labels back
        raise
    finally:
        shutil.rmtree(trash, ignore_errors=True)
