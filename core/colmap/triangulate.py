"""Sparse points for known cameras: what real SfM makes of a scene's images when the poses
and intrinsics are known (a synthetic scene's, or a calibrated rig's).

:func:`triangulate_known_poses` runs pycolmap's SIFT extraction, exhaustive matching with
geometric verification, and triangulation with point-only bundle adjustment, the poses and
intrinsics held fixed (``pycolmap.triangulate_points``). Callers: the SfM-points scene of the
acceptance study (:mod:`esgs.core.experiments.sfm_scene`) and NDN's sparse-SfM baseline
(:mod:`esgs.core.ndn.baselines`, on upscaled copies of the images).
"""
from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any, Sequence

from ..errors import DatasetError


def triangulate_known_poses(images_dir: str | Path, reference: str | Path, *,
                            camera_params: Sequence[float] | None = None, max_features: int | None = None,
                            peak_threshold: float | None = None, num_threads: int | None = None,
                            verbose: bool = False) -> Any:
    """Triangulate SIFT matches of the images of the COLMAP model in ``reference`` (a
    ``sparse/0`` folder), read from ``images_dir``, with that model's poses held fixed.

    Returns the ``pycolmap.Reconstruction``: the reference's camera (``camera_params``
    replace its parameters, e.g. scaled for upscaled images; width and height are those of the
    image files) and poses, and the triangulated points (none when the images have no
    texture or overlap: the caller decides whether that is an error). ``max_features``,
    ``peak_threshold`` and ``num_threads`` set pycolmap's SIFT extraction (None: its
    defaults). pycolmap's log is silenced unless ``verbose``.
    """
    import pycolmap

    images_dir, reference = Path(images_dir), Path(reference)
    known = pycolmap.Reconstruction(str(reference))
    if known.num_cameras() != 1:
        raise DatasetError(f"triangulation with known poses supports one camera, the scene has {known.num_cameras()}",
                           path=reference, hint="use a scene rendered with one camera model")
    camera = next(iter(known.cameras.values()))
    params = camera.params if camera_params is None else camera_params
    names = sorted(image.name for image in known.images.values())
    previous_level = pycolmap.logging.minloglevel
    if not verbose:
        pycolmap.logging.minloglevel = 2
    try:
        with tempfile.TemporaryDirectory(prefix="esgs_triangulate_") as workspace_name:
            workspace = Path(workspace_name)
            database = workspace / "database.db"
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = camera.model.name
            reader.camera_params = ",".join(repr(float(value)) for value in params)
            extraction = pycolmap.FeatureExtractionOptions()
            if max_features is not None:
                extraction.sift.max_num_features = max_features
            if peak_threshold is not None:
                extraction.sift.peak_threshold = peak_threshold
            if num_threads is not None:
                extraction.num_threads = num_threads
            pycolmap.extract_features(database, images_dir, image_names=names,
                                      camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                      extraction_options=extraction, device=pycolmap.Device.cpu)
            pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
            # the database numbers images in (multi-threaded, unordered) extraction order: build
            # the posed model with the database's ids, each pose taken from the reference by name
            posed = pycolmap.Reconstruction()
            with pycolmap.Database.open(str(database)) as opened:
                for db_camera in opened.read_all_cameras():
                    posed.add_camera_with_trivial_rig(db_camera)
                for db_image in opened.read_all_images():
                    pose = known.find_image_with_name(db_image.name).cam_from_world()
                    image = pycolmap.Image(name=db_image.name, camera_id=db_image.camera_id, image_id=db_image.image_id)
                    posed.add_image_with_trivial_frame(image, pose)
            staging = workspace / "model"
            staging.mkdir()
            return pycolmap.triangulate_points(posed, database, images_dir, staging, clear_points=True,
                                               options=pycolmap.IncrementalPipelineOptions(), refine_intrinsics=False)
    finally:
        pycolmap.logging.minloglevel = previous_level
