"""Scene folders from a set of photographs: structure from motion with pycolmap (CPU).

``scene_from_images`` runs SIFT extraction, exhaustive or sequential matching and
incremental mapping in a temporary workspace, checks that the result is one reliable model
(enough matches, real parallax, one connected model, most images registered), undistorts it
to PINHOLE cameras when the camera model has distortion, and writes the scene folder
(``images/``, ``sparse/0``, ``sfm_report.json``) atomically. Every failure raises
:class:`DatasetError` saying what went wrong and what to try; nothing is left half-written.
"""
from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, DatasetError
from ..progress import ProgressCallback, ProgressEvent, no_progress
from ..formats.scene_dir import SceneDir
from .common import check_readable, list_images, scene_provenance

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclass
class SfmOptions:
    """Settings of ``esgs dataset from-images``."""

    matcher: str = field(default="exhaustive", metadata={"help": "exhaustive (every pair) or sequential (neighbours in name order)"})
    single_camera: bool = field(default=False, metadata={"help": "all images share one camera (same sensor, lens and zoom)"})
    camera_model: str = field(default="SIMPLE_RADIAL", metadata={"help": "COLMAP camera model: " + ", ".join(CAMERA_MODELS)})
    camera_params: str = field(default="", metadata={"help": "known intrinsics in COLMAP order for --camera-model, comma-separated (e.g. PINHOLE: fx,fy,cx,cy)"})
    refine_intrinsics: bool = field(default=True, metadata={"help": "refine focal length and distortion in bundle adjustment (turn off for calibrated cameras)"})
    max_image_size: int = field(default=3200, metadata={"help": "images are downscaled to this size for feature extraction"})
    verbose: bool = field(default=False, metadata={"help": "show pycolmap's own log (otherwise only its errors)"})
    max_features: int = field(default=8192, metadata={"help": "SIFT features per image"})
    sequential_overlap: int = field(default=10, metadata={"help": "sequential matcher: neighbours matched on each side"})
    min_matches: int = field(default=15, metadata={"help": "verified matches for a pair of images to count as linked"})
    init_min_triangulation_angle_deg: float = field(default=4.0, metadata={"help": "initial pair: minimum triangulation angle (COLMAP's 16 picked a wrong, planar-ambiguous start on rover traverses)"})
    init_min_inliers: int = field(default=50, metadata={"help": "initial pair: minimum verified matches"})
    min_registered_fraction: float = field(default=0.5, metadata={"help": "fail when fewer images than this fraction get a pose"})
    min_triangulation_angle_deg: float = field(default=2.0, metadata={"help": "fail when the median triangulation angle is below this (no parallax)"})
    overwrite: bool = field(default=False, metadata={"help": "replace an existing output folder"})

    def validate(self) -> None:
        if self.matcher not in ("exhaustive", "sequential"):
            raise ConfigError(f"matcher {self.matcher!r} must be 'exhaustive' or 'sequential'")
        if self.camera_model not in CAMERA_MODELS:
            raise ConfigError(f"camera model {self.camera_model!r} is not one of {', '.join(CAMERA_MODELS)}")
        if not 0.0 < self.min_registered_fraction <= 1.0:
            raise ConfigError(f"min_registered_fraction {self.min_registered_fraction} must be in (0, 1]")
        if self.camera_params:
            from ..colmap.camera_models import model_info

            try:
                values = [float(v) for v in self.camera_params.split(",")]
            except ValueError:
                raise ConfigError(f"camera_params {self.camera_params!r} must be comma-separated numbers") from None
            expected = model_info(self.camera_model).num_params
            if len(values) != expected:
                raise ConfigError(f"camera model {self.camera_model} takes {expected} parameters, camera_params has {len(values)}")
        elif not self.refine_intrinsics:
            raise ConfigError("refine_intrinsics=False needs camera_params (the known intrinsics)")


def choose_model(names_by_model: dict, images_dir: Path) -> Any:
    """The key of the one model to keep from incremental mapping's models {key: image names}.

    The mapper may start a second model from pairs left over after the first, holding images
    the first one has registered already: such models add nothing and are dropped. Models
    with images of their own are disconnected groups: a :class:`DatasetError` naming them.
    """
    largest = max(names_by_model, key=lambda key: len(names_by_model[key]))
    covered = set(names_by_model[largest])
    separate = {key: names for key, names in names_by_model.items() if key != largest and not set(names) <= covered}
    if separate:
        groups = {largest: names_by_model[largest], **separate}
        sizes = ", ".join(f"{len(v)} images (e.g. {v[0]})" for v in groups.values())
        raise DatasetError(
            f"SfM found {len(groups)} disconnected models: {sizes}",
            path=images_dir,
            hint="the groups do not overlap enough; add linking images or process each group separately",
        )
    return largest


def _median_triangulation_angle_deg(reconstruction) -> float:
    """Median over 3D points of the largest angle between two rays of its track (degrees)."""
    centres = {image_id: np.asarray(image.projection_center()) for image_id, image in reconstruction.images.items() if image.has_pose}
    angles = []
    for point in reconstruction.points3D.values():
        ids = [element.image_id for element in point.track.elements if element.image_id in centres]
        if len(ids) < 2:
            continue
        rays = np.stack([np.asarray(point.xyz) - centres[i] for i in ids])
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        cosines = np.clip(rays @ rays.T, -1.0, 1.0)
        angles.append(np.degrees(np.arccos(cosines.min())))
    return float(np.median(angles)) if angles else 0.0


def _pair_statistics(database_path: Path) -> dict[str, Any]:
    """Counts of verified pairs by two-view configuration, read from the COLMAP database."""
    import pycolmap

    configurations: dict[str, int] = {}
    linked = 0
    with pycolmap.Database.open(str(database_path)) as database:
        pair_ids, geometries = database.read_two_view_geometries()
        for geometry in geometries:
            if len(geometry.inlier_matches) == 0:
                continue
            linked += 1
            config = geometry.config
            name = config.name if hasattr(config, "name") else pycolmap.TwoViewGeometryConfiguration(int(config)).name
            configurations[name] = configurations.get(name, 0) + 1
        images = database.num_images()
    return {"verified_pairs": linked, "configurations": configurations, "images": images}


def _rotation_only_hint() -> str:
    return (
        "the images look like a rotation-only set (camera turned about one point: no parallax). "
        "Use `esgs dataset rotation-only IMAGES --focal-px F` for a rotation-only model, or take images from several positions"
    )


def scene_from_images(
    images_dir: str | Path,
    out_dir: str | Path,
    options: SfmOptions | None = None,
    progress: ProgressCallback = no_progress,
) -> dict[str, Any]:
    """Structure from motion on the images of ``images_dir``; write a scene folder at ``out_dir``.

    Returns the report (also saved as ``out_dir/sfm_report.json``): registered and
    unregistered image names, number of models, points, mean reprojection error (px),
    median triangulation angle (degrees), camera model written. Raises DatasetError when
    SfM fails or its result is unreliable.
    """
    import pycolmap

    options = options or SfmOptions()
    options.validate()
    images_dir = Path(images_dir)
    files = list_images(images_dir)
    if len(files) < 2:
        raise DatasetError(
            f"structure from motion needs at least 2 images, found {len(files)}",
            path=images_dir,
            hint="add overlapping photographs taken from different positions",
        )
    check_readable(files)
    previous_level = pycolmap.logging.minloglevel
    if not options.verbose:
        pycolmap.logging.minloglevel = 2  # errors only: the report says what matters
    try:
        return _run_sfm(files, images_dir, Path(out_dir), options, progress)
    finally:
        pycolmap.logging.minloglevel = previous_level


def _run_sfm(files: list[Path], images_dir: Path, out_dir: Path, options: SfmOptions, progress: ProgressCallback) -> dict[str, Any]:
    import pycolmap

    from ..colmap.io import from_pycolmap, write_model
    from ..colmap.undistort import undistort_model
    from ..io_utils import atomic_directory, atomic_write_json

    progress(ProgressEvent(0, 4, stage="sfm", message="features"))
    with tempfile.TemporaryDirectory(prefix="esgs_sfm_") as workspace_name:
        workspace = Path(workspace_name)
        database = workspace / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = options.camera_model
        if options.camera_params:
            reader.camera_params = options.camera_params
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = options.max_image_size
        extraction.sift.max_num_features = options.max_features
        pycolmap.extract_features(
            database,
            images_dir,
            image_names=[f.name for f in files],
            camera_mode=pycolmap.CameraMode.SINGLE if options.single_camera else pycolmap.CameraMode.AUTO,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
        progress(ProgressEvent(1, 4, stage="sfm", message="matching"))
        if options.matcher == "sequential":
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = options.sequential_overlap
            pycolmap.match_sequential(database, pairing_options=pairing, device=pycolmap.Device.cpu)
        else:
            pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
        pairs = _pair_statistics(database)
        if pairs["images"] < len(files):
            raise DatasetError(
                f"features could be extracted from only {pairs['images']} of {len(files)} images", path=images_dir,
                hint="check that the images are valid photographs",
            )
        rotation_like = sum(pairs["configurations"].get(k, 0) for k in ("PANORAMIC", "PLANAR_OR_PANORAMIC"))
        if pairs["verified_pairs"] == 0:
            raise DatasetError(
                "no pair of images shares enough verified feature matches",
                path=images_dir,
                hint="images must overlap (about 60 % between neighbours) and show textured surfaces; "
                "with the sequential matcher, name the images in capture order",
            )
        progress(ProgressEvent(2, 4, stage="sfm", message="mapping"))
        mapping = pycolmap.IncrementalPipelineOptions()
        mapping.min_num_matches = options.min_matches
        mapping.min_model_size = 2 if len(files) < 10 else min(10, len(files) // 3)
        # Rover traverses look forward: allow forward motion for the initial pair, and a
        # smaller initial angle. With COLMAP's defaults a synthetic traverse of flat terrain
        # started from a wrong (planar-ambiguous) pair: 0.6 px error but 10-15 degree errors.
        mapping.mapper.init_min_tri_angle = options.init_min_triangulation_angle_deg
        mapping.mapper.init_min_num_inliers = options.init_min_inliers
        mapping.mapper.init_max_forward_motion = 1.0
        if not options.refine_intrinsics:
            mapping.ba_refine_focal_length = False
            mapping.ba_refine_extra_params = False
            mapping.mapper.abs_pose_refine_focal_length = False
            mapping.mapper.abs_pose_refine_extra_params = False
        # pycolmap writes its models as sparse/<k>, the layout of a scene folder
        mapped = SceneDir(workspace).sparse
        mapped.mkdir()
        reconstructions = pycolmap.incremental_mapping(database, images_dir, mapped, mapping)
        reconstructions = {k: r for k, r in reconstructions.items() if r.num_reg_images() >= 2}
        rotation_share = rotation_like / max(pairs["verified_pairs"], 1)
        if not reconstructions:
            if rotation_share > 0.5:
                raise DatasetError(
                    f"SfM could not initialise: {rotation_like} of {pairs['verified_pairs']} verified pairs are related by a "
                    "homography, i.e. a pure rotation (no parallax) or a flat scene seen from too little baseline",
                    path=images_dir,
                    hint=_rotation_only_hint(),
                )
            raise DatasetError(
                f"SfM could not build a model ({pairs['verified_pairs']} verified image pairs)",
                path=images_dir,
                hint="too few or unreliable matches: add images with more overlap and parallax, or try --single-camera",
            )
        names_by_model = {
            key: sorted(image.name for image in r.images.values() if image.has_pose) for key, r in reconstructions.items()
        }
        key = choose_model(names_by_model, images_dir)
        reconstruction = reconstructions[key]
        registered = names_by_model[key]
        unregistered = sorted(set(f.name for f in files) - set(registered))
        angle = _median_triangulation_angle_deg(reconstruction)
        if reconstruction.num_points3D() == 0 or angle < options.min_triangulation_angle_deg:
            raise DatasetError(
                f"SfM model has almost no parallax: median triangulation angle {angle:.2f} deg "
                f"(< {options.min_triangulation_angle_deg}), {reconstruction.num_points3D()} points",
                path=images_dir,
                hint=_rotation_only_hint(),
            )
        if len(registered) < options.min_registered_fraction * len(files):
            raise DatasetError(
                f"SfM registered only {len(registered)} of {len(files)} images; unregistered: {unregistered[:10]}",
                path=images_dir,
                hint="add overlapping images, try the exhaustive matcher, or remove images of other places",
            )
        model = from_pycolmap(reconstruction, source=str(SceneDir(out_dir).model))
        _, _, errors, _ = model.points_arrays()
        report = {
            "images": len(files),
            "registered": registered,
            "unregistered": unregistered,
            "models": len(reconstructions),
            "points": len(model.points),
            "mean_reprojection_error_px": float(errors.mean()) if len(errors) else 0.0,
            "median_triangulation_angle_deg": angle,
            "verified_pairs": pairs["verified_pairs"],
            "pair_configurations": pairs["configurations"],
            "camera_model_estimated": sorted({c.model for c in model.cameras.values()}),
            "matcher": options.matcher,
        }
        progress(ProgressEvent(3, 4, stage="sfm", message="writing"))
        distorted = any(not camera.is_pinhole for camera in model.cameras.values())
        with atomic_directory(out_dir, overwrite=options.overwrite) as staging:
            staged = SceneDir(staging)
            if distorted:
                # undistort_model builds its own folder atomically; build it inside ours.
                model = undistort_model(model, images_dir, staging / "scene")
                for child in (staging / "scene").iterdir():
                    shutil.move(str(child), staging / child.name)
                (staging / "scene").rmdir()
            else:
                staged.images.mkdir()
                for name in registered:
                    shutil.copyfile(images_dir / name, staged.image(name))
                write_model(model, staged.model, binary=True)
            report["camera_model_written"] = sorted({c.model for c in model.cameras.values()})
            atomic_write_json(staging / "sfm_report.json", report)
            atomic_write_json(staged.provenance, scene_provenance(
                "sfm", registered, units="SfM units (arbitrary scale and frame)", points3d=len(model.points), report="sfm_report.json"))
    progress(ProgressEvent(4, 4, stage="sfm", kind="done", message="done"))
    return report
