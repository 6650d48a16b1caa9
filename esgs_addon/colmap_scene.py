"""COLMAP scenes in Blender: import a sparse model as cameras, image planes and a point
cloud, and export Blender cameras as a COLMAP model.

Public API (operators and headless scripts call these):

- :func:`import_colmap_scene(path, options) -> dict` builds ONE new collection named after
  the scene, or nothing at all when it fails.
- :func:`export_cameras_to_colmap(scene_or_cameras, out_dir) -> ColmapModel` writes
  PINHOLE cameras, images and an empty points3D.

Frames: Blender's world is COLMAP's world, unless ``orient_up`` was used; then Blender's
world is ``T @ colmap_world`` with ``T`` (4x4, rigid) stored on the collection as the
custom property ``esgs_world_from_colmap``, and exports undo it.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import bpy
import numpy as np

from ..core.colmap.geometry import matrix_to_quat_wxyz
from ..core.colmap.model import Camera, ColmapModel, Image
from ..core.errors import ConfigError, DatasetError
from ..core.progress import ProgressCallback, ProgressEvent, no_progress
from ..core.formats.scene_dir import SceneDir
from . import cameras, image_planes, orient, pointcloud

#: Collection custom property: [16] row-major "Blender world from COLMAP world" transform
PROP_TRANSFORM = "esgs_world_from_colmap"
PROP_SOURCE = "esgs_colmap_source"
PROP_IMAGE_ID = "esgs_colmap_image_id"
PROP_IMAGE_NAME = "esgs_colmap_image_name"
PROP_CAMERA_ID = "esgs_colmap_camera_id"
PROP_CAMERA_MODEL = "esgs_colmap_camera_model"
PROP_CAMERA_PARAMS = "esgs_colmap_camera_params"
PROP_DISTORTION_IGNORED = "esgs_distortion_ignored"

MODEL_FILES = ("cameras", "images", "points3D")


@dataclass
class ColmapImportOptions:
    """Settings of a COLMAP import (the Blender properties are derived from these fields)."""

    import_points: bool = field(default=True, metadata={"help": "Import the sparse 3D points as a point cloud"})
    point_radius: float = field(
        default=0.0, metadata={"help": "Radius of each point in scene units (0 = automatic from the scene size)"}
    )
    image_planes: bool = field(default=False, metadata={"help": "Show each photo on a plane in front of its camera"})
    image_plane_distance: float = field(
        default=1.0, metadata={"help": "Distance of the image planes from their cameras, in scene units"}
    )
    orient_up: bool = field(
        default=False,
        metadata={"help": "Rotate the scene so the ground is horizontal and +Z points up (stored, undone on export)"},
    )
    set_scene_resolution: bool = field(
        default=True, metadata={"help": "Set the render resolution and pixel aspect from the first camera"}
    )
    undistorted_path: str = field(
        default="",
        metadata={
            "help": "Folder written by COLMAP's image_undistorter (images/ and sparse/); used instead of a "
            "model with lens distortion"
        },
    )
    collection_name: str = field(default="", metadata={"help": "Name of the new collection (empty = scene folder name)"})

    def validate(self) -> None:
        if self.point_radius < 0:
            raise ConfigError(f"point_radius must be >= 0, got {self.point_radius}")
        if self.image_plane_distance <= 0:
            raise ConfigError(f"image_plane_distance must be > 0, got {self.image_plane_distance}")


# ----------------------------------------------------------------------------- locating


def _has_model(folder: Path) -> bool:
    return all((folder / f"{name}.bin").is_file() or (folder / f"{name}.txt").is_file() for name in MODEL_FILES)


def locate_scene(path: str | Path) -> tuple[Path, Path | None, str]:
    """(model folder, images folder or None, scene name) for a scene folder or a model folder.

    Accepts ``SCENE`` (with ``sparse/0`` or ``sparse``), or the model folder itself; images
    are looked for in ``SCENE/images`` or beside/above the model folder.
    """
    path = Path(path).expanduser()
    if not path.is_dir():
        raise DatasetError("folder not found", path=path, hint="choose a scene folder holding images/ and sparse/0")
    scene = SceneDir(path)
    candidates = [path, scene.model, scene.sparse]
    model_dir = next((folder for folder in candidates if _has_model(folder)), None)
    if model_dir is None:
        raise DatasetError(
            "no COLMAP model found (cameras, images and points3D as .bin or .txt)",
            path=path,
            hint="choose the scene folder holding sparse/0, or the model folder itself",
        )
    if model_dir == path:
        # a model folder: SCENE/sparse/0 -> SCENE, SCENE/sparse_txt -> SCENE
        above = SceneDir(path.parent.parent)
        root = above.root if path.parent == above.sparse else path.parent
    else:
        root = path
    image_candidates = [SceneDir(root).images, scene.images, SceneDir(model_dir.parent).images]
    images_dir = next((folder for folder in image_candidates if folder.is_dir()), None)
    name = root.name or path.name or "COLMAP"
    return model_dir, images_dir, name


# ----------------------------------------------------------------------------- helpers


_ID_COLLECTIONS = ("objects", "cameras", "meshes", "materials", "images", "pointclouds", "collections")


@contextlib.contextmanager
def _all_or_nothing() -> Iterator[None]:
    """Remove every datablock created inside the block when it raises."""
    before = {name: {block.session_uid for block in getattr(bpy.data, name)} for name in _ID_COLLECTIONS}
    try:
        yield
    except BaseException:
        created = [
            block
            for name in _ID_COLLECTIONS
            for block in getattr(bpy.data, name)
            if block.session_uid not in before[name]
        ]
        if created:
            bpy.data.batch_remove(created)
        raise


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear (Blender's float colours are scene-linear)."""
    values = np.asarray(values, dtype=np.float64)
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)


def automatic_point_radius(xyz: np.ndarray) -> float:
    """A point radius that reads well at the scene's size: 0.15 % of its robust diagonal."""
    if len(xyz) < 2:
        return 0.01
    low, high = np.percentile(xyz, [2, 98], axis=0)
    diagonal = float(np.linalg.norm(high - low))
    return 0.0015 * diagonal if diagonal > 0 else 0.01


def _transform_points(transform: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    return xyz @ transform[:3, :3].T + transform[:3, 3]


def _read_model(model_dir: Path) -> ColmapModel:
    from ..core.colmap.io import read_model

    return read_model(model_dir)


def _distortion_warning(camera: Camera) -> str:
    return (
        f"camera {camera.camera_id} uses the {camera.model} model: its lens distortion cannot be shown by a "
        f"Blender camera and was NOT applied (parameters kept as custom properties on the cameras); "
        f"undistort the scene (esgs.core.colmap.undistort.undistort_model or COLMAP's image_undistorter) "
        f"and set 'Undistorted path' for exact views"
    )


# ----------------------------------------------------------------------------- import


def import_colmap_scene(
    path: str | Path,
    options: ColmapImportOptions | None = None,
    scene: bpy.types.Scene | None = None,
    progress: ProgressCallback = no_progress,
) -> dict:
    """Import a COLMAP scene into ``scene`` (default: the context's) as one new collection.

    Returns ``{"collection": Collection, "cameras": [Object], "points": Object | None,
    "image_planes": [Object], "transform": [4, 4] ndarray (Blender from COLMAP world),
    "warnings": [str], "model": ColmapModel, "model_path": str, "images_path": str | None}``.
    Raises :class:`~esgs.core.errors.ESGSError` (and creates nothing) on bad input.
    """
    options = options or ColmapImportOptions()
    options.validate()
    scene = scene or bpy.context.scene
    warnings: list[str] = []

    source = Path(options.undistorted_path).expanduser() if options.undistorted_path else Path(path).expanduser()
    model_dir, images_dir, scene_name = locate_scene(source)
    if options.undistorted_path:
        scene_name = Path(path).expanduser().name or scene_name  # named after the scene, not "dense"
    model = _read_model(model_dir)
    if not model.images:
        raise DatasetError("the model has no registered images", path=model_dir)
    if options.undistorted_path and not all(camera.is_pinhole for camera in model.cameras.values()):
        raise DatasetError(
            "the undistorted model still has cameras with distortion",
            path=model_dir,
            hint="point 'Undistorted path' at an undistorted scene (images/ and sparse/0 with PINHOLE cameras)",
        )
    for camera in sorted(model.cameras.values(), key=lambda c: c.camera_id):
        if not camera.is_pinhole:
            warnings.append(_distortion_warning(camera))
    images = model.sorted_images()
    if options.image_planes and images_dir is None:
        warnings.append(f"no images/ folder found near {model_dir}: image planes were skipped")

    # the orientation transform, from the cameras and points as COLMAP gives them
    xyz, rgb, error, track_length = model.points_arrays()
    transform = np.eye(4)
    if options.orient_up:
        poses = np.stack([image.world_to_camera() for image in images])
        transform = orient.up_alignment_transform(poses, xyz if len(xyz) else None)
    colmap_from_blender = np.linalg.inv(transform)

    total = len(images) + 1
    result: dict = {"warnings": warnings, "model": model, "model_path": str(model_dir),
                    "images_path": str(images_dir) if images_dir else None, "transform": transform}
    with _all_or_nothing():
        collection = bpy.data.collections.new(options.collection_name or scene_name)
        scene.collection.children.link(collection)
        collection[PROP_TRANSFORM] = [float(v) for v in transform.reshape(-1)]
        collection[PROP_SOURCE] = str(model_dir)
        camera_objects: list[bpy.types.Object] = []
        planes: list[bpy.types.Object] = []
        for step, image in enumerate(images):
            camera = model.cameras.get(image.camera_id)
            if camera is None:
                raise DatasetError(f"image '{image.name}' refers to missing camera {image.camera_id}", path=model_dir)
            K = camera.K()
            world_to_camera = image.world_to_camera() @ colmap_from_blender
            obj = cameras.camera_object_from_opencv(image.name, K, world_to_camera, camera.width, camera.height, collection)
            obj[PROP_IMAGE_ID] = int(image.image_id)
            obj[PROP_IMAGE_NAME] = image.name
            obj[PROP_CAMERA_ID] = int(camera.camera_id)
            obj[PROP_CAMERA_MODEL] = camera.model
            obj[PROP_CAMERA_PARAMS] = [float(v) for v in np.asarray(camera.params).reshape(-1)]
            obj[PROP_DISTORTION_IGNORED] = not camera.is_pinhole
            camera_objects.append(obj)
            if options.image_planes and images_dir is not None:
                image_path = images_dir / image.name
                if not image_path.is_file():
                    warnings.append(f"{image_path}: image not found, no image plane for it")
                else:
                    picture = image_planes.load_image(image_path)
                    planes.append(
                        image_planes.image_plane_object(
                            f"{image.name} plane", obj, K, camera.width, camera.height, picture,
                            options.image_plane_distance, collection,
                        )
                    )
            progress(ProgressEvent(step=step + 1, total=total, stage="import cameras"))

        points_object = None
        if options.import_points and len(xyz):
            positions = _transform_points(transform, xyz)
            colours = np.ones((len(xyz), 4))
            colours[:, :3] = srgb_to_linear(rgb / 255.0)
            radius = options.point_radius or automatic_point_radius(positions)
            points_object = pointcloud.point_cloud_object(
                f"{collection.name} points",
                positions,
                {
                    pointcloud.COLOR_ATTRIBUTE: colours,
                    pointcloud.RENDER_COLOR_ATTRIBUTE: rgb,
                    "error": error.astype(np.float32),
                    "track_length": track_length,
                },
                radius=radius,
                collection=collection,
                material=pointcloud.point_color_material(),
            )
        progress(ProgressEvent(step=total, total=total, stage="import points", kind="done"))

        if options.set_scene_resolution:
            first = model.cameras[images[0].camera_id]
            fx, fy, _, _ = first.intrinsics()
            sizes = {(c.width, c.height) for c in model.cameras.values()}
            if len(sizes) > 1:
                warnings.append(
                    f"the model's cameras have {len(sizes)} different image sizes; the render resolution is "
                    f"{first.width}x{first.height} (of '{images[0].name}'); use esgs_addon.cameras.use_camera "
                    "to switch to another camera's resolution"
                )
            cameras.set_scene_resolution_from_camera(scene, first.width, first.height, fx, fy)
            scene.camera = camera_objects[0]

    result.update(collection=collection, cameras=camera_objects, points=points_object, image_planes=planes)
    return result


# ----------------------------------------------------------------------------- export


def world_from_colmap_of(obj: bpy.types.Object) -> np.ndarray:
    """[4, 4] the orientation transform stored on the object's collection (identity if none)."""
    for collection in obj.users_collection:
        value = collection.get(PROP_TRANSFORM)
        if value is not None:
            return np.array(value, dtype=np.float64).reshape(4, 4)
    return np.eye(4)


def _camera_objects(scene_or_cameras: bpy.types.Scene | Iterable[bpy.types.Object]) -> list[bpy.types.Object]:
    if isinstance(scene_or_cameras, bpy.types.Scene):
        objects = [obj for obj in scene_or_cameras.objects if obj.type == "CAMERA"]
    else:
        objects = list(scene_or_cameras)
        for obj in objects:
            if obj.type != "CAMERA":
                raise ConfigError(f"object '{obj.name}' is a {obj.type}, not a camera")
    if not objects:
        raise ConfigError("there are no cameras to export", hint="add or select camera objects")
    return sorted(objects, key=lambda obj: obj.name)


def export_cameras_to_colmap(
    scene_or_cameras: bpy.types.Scene | Sequence[bpy.types.Object],
    out_dir: str | Path,
    scene: bpy.types.Scene | None = None,
    binary: bool = True,
    overwrite: bool = False,
) -> ColmapModel:
    """Write Blender cameras as a COLMAP model (PINHOLE cameras, images, empty points3D).

    Intrinsics use the active scene resolution (``scene``, default: the given scene or the
    context's). Each camera's orientation transform (stored on its collection by an
    ``orient_up`` import) is undone, so the poses are in the original COLMAP frame. Image
    names and ids of imported cameras are kept; other cameras get ``<object name>.png``.
    Identical intrinsics share one COLMAP camera. The folder is written atomically; an
    existing non-empty ``out_dir`` is replaced only with ``overwrite``. Returns the model.
    """
    from ..core.colmap.io import write_model

    if scene is None:
        scene = scene_or_cameras if isinstance(scene_or_cameras, bpy.types.Scene) else bpy.context.scene
    objects = _camera_objects(scene_or_cameras)

    model_cameras: dict[int, Camera] = {}
    camera_keys: dict[tuple, int] = {}
    model_images: dict[int, Image] = {}
    stored_ids = [int(obj[PROP_IMAGE_ID]) for obj in objects if PROP_IMAGE_ID in obj]
    keep_ids = len(set(stored_ids)) == len(stored_ids)  # imported ids survive unless duplicated
    next_id = (max(stored_ids) if stored_ids else 0) + 1
    names: set[str] = set()
    for obj in objects:
        K, world_to_camera, width, height = cameras.opencv_from_camera_object(obj, scene)
        world_to_camera = world_to_camera @ world_from_colmap_of(obj)
        params = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        key = (width, height, *params.tolist())
        if key not in camera_keys:
            camera_keys[key] = len(camera_keys) + 1
            model_cameras[camera_keys[key]] = Camera(camera_keys[key], "PINHOLE", width, height, params)
        if keep_ids and PROP_IMAGE_ID in obj:
            image_id = int(obj[PROP_IMAGE_ID])
        else:
            image_id, next_id = next_id, next_id + 1
        name = str(obj.get(PROP_IMAGE_NAME, f"{obj.name}.png"))
        if name in names:
            raise ConfigError(f"two cameras would write the same image name '{name}'", hint="rename one of them")
        names.add(name)
        model_images[image_id] = Image(
            image_id=image_id,
            name=name,
            camera_id=camera_keys[key],
            quat_wxyz=matrix_to_quat_wxyz(world_to_camera[:3, :3]),
            translation=world_to_camera[:3, 3].copy(),
        )
    model = ColmapModel(cameras=model_cameras, images=model_images, points={}, source=str(out_dir))
    write_model(model, out_dir, binary=binary, overwrite=overwrite)
    return model
