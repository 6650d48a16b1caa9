"""Sparse SfM depth priors: each view's triangulated COLMAP points, projected into it."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..colmap import ColmapModel
from ..progress import ProgressCallback, ProgressEvent, no_progress
from ..io_utils import atomic_directory
from ..formats.scene_dir import SceneDir
from .io import prior_dir, write_prior_maps


def sparse_depth_map(model: ColmapModel, image_id: int, *, max_error_px: float = 2.0,
                     min_track_length: int = 2) -> np.ndarray:
    """[H, W] float32 depth (camera z) at the pixels where the image observes a 3D point; 0 elsewhere.

    Uses the image's own observations (its 2D keypoints linked to 3D points), keeping points
    with reprojection error <= ``max_error_px`` and track length >= ``min_track_length``; where
    two points fall in one pixel the nearer wins (it occludes the other).
    """
    image = model.images[image_id]
    camera = model.cameras[image.camera_id]
    depth = np.zeros((camera.height, camera.width), np.float32)
    xyz, pixels = model.observed_points(image_id, max_error_px=max_error_px, min_track_length=min_track_length)
    if len(xyz) == 0:
        return depth
    rotation = image.rotation_matrix()
    z = (xyz @ rotation.T + image.translation)[:, 2]
    columns = np.floor(pixels[:, 0]).astype(int)
    rows = np.floor(pixels[:, 1]).astype(int)
    inside = (z > 0) & (columns >= 0) & (columns < camera.width) & (rows >= 0) & (rows < camera.height)
    order = np.argsort(-z[inside])  # far first, so nearer points overwrite them
    depth[rows[inside][order], columns[inside][order]] = z[inside][order]
    return depth


def write_sfm_priors(scene_dir: str | Path, model: ColmapModel, progress: ProgressCallback = no_progress,
                     **options) -> int:
    """Write ``priors/sfm/depth`` and ``mask`` for every registered image; returns the count.

    The maps are written to a staging folder that replaces ``priors/sfm`` only when every view
    is done, so a failure or an interrupt keeps the previous priors (or leaves none).
    """
    scene_dir = Path(scene_dir)
    images = model.sorted_images()
    priors = SceneDir(scene_dir).priors
    priors.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".sfm.work.", dir=priors))
    try:
        prior_dir(work, "sfm").mkdir(parents=True)
        for index, image in enumerate(images):
            depth = sparse_depth_map(model, image.image_id, **options)
            write_prior_maps(work, "sfm", image.name, depth=depth, mask=depth > 0, units="sfm",
                             metadata={"note": "sparse: projected COLMAP points"})
            progress(ProgressEvent(step=index + 1, total=len(images), stage="sfm priors"))
        with atomic_directory(prior_dir(scene_dir, "sfm"), overwrite=True) as staging:
            os.replace(prior_dir(work, "sfm"), staging)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return len(images)
