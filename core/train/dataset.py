"""Training views from a COLMAP scene folder (``images/`` + ``sparse/0``).

- images are read once, downscaled (``resolution`` factor or target ``width``, area
  filter) and kept as uint8 to save memory; intrinsics are scaled with them (pixel centres
  at +0.5, so scaling fx, fy, cx, cy by the size ratio is exact);
- cameras with distortion are undistorted to PINHOLE first (:mod:`esgs.core.colmap.undistort`);
- the split is 3DGS's: images sorted by name, index % test_every == 0 are held out;
- the scene extent is 3DGS's: 1.1 x the largest distance of a training camera centre from
  their mean (``radius``), which scales position learning rates and size thresholds;
- optional sky masks from ``priors/<source>/mask/<stem>.png`` (255 = valid surface).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..errors import DatasetError
from ..formats.scene_dir import PriorSource, SceneDir


@dataclass
class View:
    """One posed image.

    K: [3, 3] float32; viewmat: [4, 4] float32 world-to-camera (OpenCV axes); image:
    [H, W, 3] uint8; mask: [H, W, 1] bool (True = counts in the loss) or None;
    center: [3] camera centre in world coordinates (float64). observed_xyz: [M, 3] world
    coordinates (float64) of the SfM points this image observes (well-fitted, seen by two or
    more images), which pin relative depth priors to the scene's scale.
    """

    index: int
    name: str
    K: torch.Tensor
    viewmat: torch.Tensor
    width: int
    height: int
    image: torch.Tensor
    mask: Optional[torch.Tensor] = None
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    observed_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    def image_float(self, device: torch.device | str = "cpu") -> torch.Tensor:
        """[H, W, 3] float32 in [0, 1]."""
        return self.image.to(device=device, dtype=torch.float32) / 255.0


@dataclass
class SceneData:
    """Views of a scene split into train and test, the SfM points and the scene extent."""

    train: list[View]
    test: list[View]
    points_xyz: np.ndarray  # [P, 3] float64
    points_rgb: np.ndarray  # [P, 3] float in [0, 1]
    extent: float
    center: np.ndarray  # [3] mean of the training camera centres
    mask_source: Optional[str] = None
    source: Optional[Path] = None


def split_indices(count: int, test_every: int) -> tuple[list[int], list[int]]:
    """(train, test) indices of images sorted by name: index % test_every == 0 is test (3DGS)."""
    if test_every <= 0:
        return list(range(count)), []
    test = [i for i in range(count) if i % test_every == 0]
    train = [i for i in range(count) if i % test_every != 0]
    return train, test


def scene_extent(centers: np.ndarray) -> tuple[float, np.ndarray]:
    """3DGS's scene radius: 1.1 x max distance of the camera centres [M, 3] from their mean."""
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    mean = centers.mean(axis=0)
    radius = float(np.linalg.norm(centers - mean, axis=1).max()) if len(centers) else 0.0
    # a single camera (or cameras at one spot) would give a zero extent and zero learning rates
    return 1.1 * (radius if radius > 0 else 1.0), mean


def target_size(width: int, height: int, resolution: int, target_width: int) -> tuple[int, int]:
    """Image size after downscaling by ``resolution`` or to ``target_width`` (aspect kept)."""
    if target_width > 0:
        scale = target_width / width
    else:
        scale = 1.0 / resolution
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))


def _read_rgb(path: Path) -> np.ndarray:
    """[H, W, 3] uint8 RGB (grey images expanded; see :func:`esgs.core.formats.imageio.read_image`)."""
    from ..formats.imageio import read_image

    image = read_image(path)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    return np.ascontiguousarray(image)


def _resize(image: np.ndarray, size: tuple[int, int], nearest: bool = False) -> np.ndarray:
    import cv2

    if (image.shape[1], image.shape[0]) == size:
        return image
    interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
    return cv2.resize(image, size, interpolation=interpolation)


def find_mask_source(scene: Path, requested: str) -> Optional[str]:
    """The priors source whose mask/ folder to use: the requested name; for 'auto' gt, else a source
    whose sky maps mark sky somewhere (ndn), else the first dense mask found; None for 'none'."""
    if requested == "none":
        return None
    folder = SceneDir(scene)
    if requested == "auto":
        # only dense masks: sfm's marks the sparse pixels with a depth sample, and using it for
        # the photometric loss would blank most of the image
        found = [source for source in PriorSource.auto_mask_order() if folder.has_prior_maps(source, "mask")]
        if not found or found[0] is PriorSource.GT:
            return found[0].value if found else None  # the scene's exact masks when it has them
        # then a source that marked sky in its sky/ maps (ndn, with the normals network's sky)
        # before a mask that only says where a source has values (labels): the trainer's sky
        # terms need the sky marked (measured on scenes without ground truth: docs/training.md,
        # "Sky masks from the normals network")
        for source in found:
            if source.masks_sky and _marks_sky_somewhere(folder, source):
                return source.value
        return found[0].value
    if not folder.has_prior_maps(requested, "mask"):
        raise DatasetError(f"no mask folder for prior source {requested!r}", path=folder.prior_maps(requested, "mask"),
                           hint="use --mask-source auto or none")
    return requested


def _marks_sky_somewhere(folder: SceneDir, source: PriorSource) -> bool:
    """Whether ``priors/<source>/sky/`` holds a map with at least one sky pixel (read until one does)."""
    import cv2

    sky = folder.prior_maps(source, "sky")
    for path in sorted(sky.glob("*.png")) if sky.is_dir() else []:
        raw = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if raw is not None and int(raw.max()) > 127:
            return True
    return False


def _read_mask(path: Path) -> np.ndarray:
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if raw is None:
        raise DatasetError("cannot read mask image", path=path, hint="masks are 8-bit PNGs, 255 = valid surface")
    return raw


def _mask_tensor(raw: np.ndarray, size: tuple[int, int]) -> torch.Tensor:
    """[H, W, 1] bool: area-average then threshold, so a downscaled pixel counts when mostly valid."""
    resized = _resize(raw.astype(np.float32), size)
    return torch.from_numpy(resized >= 127.5)[:, :, None]


class _Undistorter:
    """Warps images of distorted cameras to their PINHOLE equivalent (COLMAP's choice of size)."""

    def __init__(self) -> None:
        self._cache: dict[int, tuple] = {}

    def camera(self, camera):
        if camera.is_pinhole:
            return camera
        return self._entry(camera)[0]

    def _entry(self, camera):
        if camera.camera_id not in self._cache:
            from ..colmap.undistort import undistorted_camera, undistortion_maps

            pinhole = undistorted_camera(camera)
            self._cache[camera.camera_id] = (pinhole, undistortion_maps(camera, pinhole))
        return self._cache[camera.camera_id]

    def image(self, pixels: np.ndarray, camera, *, nearest: bool = False) -> np.ndarray:
        if camera.is_pinhole:
            return pixels
        from ..colmap.undistort import undistort_image

        pinhole, maps = self._entry(camera)
        return undistort_image(pixels, camera, pinhole, maps=maps, interpolation="nearest" if nearest else "linear")


def check_scene_folder(scene: str | Path, images_dir: str = "images") -> None:
    """The cheap checks of a scene folder (it exists, has its image folder and a COLMAP model):
    a :class:`DatasetError` naming what is missing, before anything is written for a run."""
    from ..colmap.io import find_model_dir

    scene = Path(scene)
    if not scene.is_dir():
        raise DatasetError("scene folder not found", path=scene, hint="pass a folder holding images/ and sparse/0")
    folder = scene / images_dir
    if not folder.is_dir():
        raise DatasetError("scene has no image folder", path=folder, hint="COLMAP scenes keep their images in images/")
    find_model_dir(scene)


def load_scene_data(scene: str | Path, *, images_dir: str = "images", resolution: int = 1, width: int = 0,
                    test_every: int = 8, mask_source: str = "auto") -> SceneData:
    """Read a COLMAP scene folder into train/test :class:`View` lists (see the module docstring)."""
    from ..colmap.io import read_model

    scene = Path(scene)
    check_scene_folder(scene, images_dir)
    folder = scene / images_dir
    # The project's checked parser gives the same model as pycolmap (tests/core/test_colmap_io.py)
    # without importing pycolmap (~56 MiB resident) or building its per-point objects.
    model = read_model(scene, use_pycolmap=False)
    undistorter = _Undistorter()
    images = model.sorted_images()
    if not images:
        raise DatasetError("the COLMAP model has no registered images", path=SceneDir(scene).sparse)
    source = find_mask_source(scene, mask_source)

    views = []
    for index, entry in enumerate(images):
        path = folder / entry.name
        if not path.is_file():
            raise DatasetError(f"image {entry.name} of the COLMAP model is missing", path=path)
        distorted = model.cameras[entry.camera_id]
        pixels = _read_rgb(path)
        height, width_px = pixels.shape[:2]
        if (width_px, height) != (distorted.width, distorted.height):
            raise DatasetError(f"image is {width_px}x{height} but its camera {distorted.camera_id} is "
                               f"{distorted.width}x{distorted.height}", path=path, hint="re-export the images or the model")
        camera = undistorter.camera(distorted)
        size = target_size(camera.width, camera.height, resolution, width)
        pixels = _resize(undistorter.image(pixels, distorted), size)
        fx, fy, cx, cy = camera.intrinsics()
        sx, sy = size[0] / camera.width, size[1] / camera.height
        K = torch.tensor([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]], dtype=torch.float32)
        mask = None
        if source is not None:
            # the file stem only (sub-folders dropped), as this loader has always looked masks up
            mask_path = SceneDir(scene).mask_map(source, Path(entry.name).name)
            if mask_path.is_file():
                raw = _read_mask(mask_path)
                if raw.shape != (distorted.height, distorted.width):
                    raise DatasetError(f"mask is {raw.shape[1]}x{raw.shape[0]}, its image is {distorted.width}x"
                                       f"{distorted.height}", path=mask_path)
                mask = _mask_tensor(undistorter.image(raw, distorted, nearest=True), size)
        views.append(View(index=index, name=entry.name, K=K,
                          viewmat=torch.from_numpy(entry.world_to_camera()).float(), width=size[0], height=size[1],
                          image=torch.from_numpy(pixels), mask=mask, center=entry.camera_center(),
                          observed_xyz=model.observed_points(entry.image_id)[0]))

    train_idx, test_idx = split_indices(len(views), test_every)
    if not train_idx:
        raise DatasetError("no training images left after the test split", path=scene,
                           hint="use more images or --test-every 0")
    train = [views[i] for i in train_idx]
    test = [views[i] for i in test_idx]
    extent, center = scene_extent(np.stack([v.center for v in train]))
    xyz, rgb, _, _ = model.points_arrays()
    return SceneData(train=train, test=test, points_xyz=xyz, points_rgb=rgb.astype(np.float64) / 255.0,
                     extent=extent, center=center, mask_source=source, source=scene)
