"""Training data for NDN: view triples with depth/normal/mask targets at the working resolution.

A *triple* is a reference view plus its two nearest neighbours (camera centres close and
viewing directions alike). The data builder renders synthetic scenes with ``esgs scene``
(one child process per scene), turns every view of a scene into a triple and stores the
scene as one npz shard:

- ``views`` [N, 9, h, w] uint8: reference RGB, neighbour 1 RGB, neighbour 2 RGB;
- ``depth`` [N, h, w] float32: z depth in metres (0 = no surface);
- ``normal`` [N, 3, h, w] float32: unit normals in the camera frame (OpenCV axes), 0 = none;
- ``mask`` [N, h, w] bool: valid surface;
- ``sfm_depth`` [N, h, w] float32 (shards built with SfM points): the z depth of the points
  triangulated from the scene's rendered images with its known poses (SIFT, matching,
  triangulation: what a real capture gives, not the generator's exact samples), the median
  of the points in each working pixel, 0 where none falls (:mod:`.evidence`).

The diffusion targets are derived on the fly from the stored metric depth (so one data
folder serves every kind of state): :func:`depth_to_state` maps depth to [-1, 1] per view
(no surface = +1, far). The ``affine`` state maps it affinely (nearest surface -1, farthest
+1); the ``log`` state is ``ln(depth / reference) / c`` with a per-view reference depth and
a fixed ``c`` (the model's ``log_depth_range``). Either way :func:`state_to_relative_depth`
inverts it to a *relative* depth that is affine in true depth (the log state's is true
depth times one unknown scale), which the trainer's prior losses recover with
``fit_scale_shift``.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ConfigError, DatasetError, ESGSError
from ..io_utils import atomic_path, atomic_write_json
from ..progress import ProgressCallback, ProgressEvent, no_progress
from ..formats.scene_dir import SceneDir
from .config import DEPTH_STATES, NDNDataConfig

if TYPE_CHECKING:
    import torch

SHARD_FORMAT = "esgs-ndn-shard-1"
TRAIN_PRESETS = NDNDataConfig().presets  # every preset without sky
HELDOUT_SEED_OFFSET = 100_000  # held-out scenes use seeds >= this; training scenes never do
# validation scenes (model selection during training) use seeds in [VALIDATION_SEED_OFFSET,
# HELDOUT_SEED_OFFSET): never a training seed (those stay below) nor a held-out one
VALIDATION_SEED_OFFSET = 50_000
SPLITS = ("train", "validation", "heldout")


def working_shape(width: int, height: int, working_size: int, multiple: int) -> tuple[int, int]:
    """(w, h) at the working resolution: long side ``working_size``, both multiples of ``multiple``."""
    scale = working_size / max(width, height)
    out_width = max(multiple, int(round(width * scale / multiple)) * multiple)
    out_height = max(multiple, int(round(height * scale / multiple)) * multiple)
    return out_width, out_height


def neighbour_indices(centres: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """For each camera, its two best neighbours: [N, 3] centres and [N, 3] unit viewing
    directions -> [N, 2] indices. Score = distance / median spacing + (1 - cos angle), so
    close cameras looking the same way (overlapping views) win. A scene with fewer than
    three views repeats what it has (a lone view is its own neighbour)."""
    count = len(centres)
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    spacing = np.median(distance[distance > 0]) if (distance > 0).any() else 1.0
    score = distance / spacing + (1.0 - directions @ directions.T)
    np.fill_diagonal(score, np.inf)
    order = np.argsort(score, axis=1)
    result = np.zeros((count, 2), np.int64)
    for index in range(count):
        others = [int(j) for j in order[index] if j != index][:2]
        while len(others) < 2:
            others.append(others[-1] if others else index)
        result[index] = others
    return result


LOG_DEPTH_RANGE = 2.5  # default c of the log state (NDNDiffusionConfig.log_depth_range)
# the log state's per-view reference depth is the geometric mean of these percentiles of the
# valid depths: the middle of the view's log-depth range (so a fixed c clips least), and a few
# stray pixels at either end cannot move it
LOG_REFERENCE_PERCENTILES = (2.0, 98.0)


def _check_kind(kind: str) -> None:
    if kind not in DEPTH_STATES:
        raise ConfigError(f"depth state must be one of {', '.join(DEPTH_STATES)}, got {kind!r}")


def depth_to_state(depth: np.ndarray, mask: np.ndarray, kind: str = "affine",
                   log_range: float = LOG_DEPTH_RANGE) -> np.ndarray:
    """Relative depth state in [-1, 1]: [H, W] depth, [H, W] bool mask -> [H, W] float32.

    ``kind`` "affine": affine per view (nearest surface -1, farthest +1). "log":
    ``clip(ln(depth / reference) / log_range, -1, 1)`` with ``reference`` the geometric mean of
    the 2nd and 98th percentiles of the view's valid depths, so a relative error of the depth
    is ``log_range`` x the state's error at every range. No-surface pixels are +1 (far).
    """
    _check_kind(kind)
    valid = mask & (depth > 0) & np.isfinite(depth)
    state = np.ones(depth.shape, np.float32)
    if valid.any():
        values = depth[valid].astype(np.float64)
        if kind == "affine":
            low, high = float(values.min()), float(values.max())
            span = max(high - low, 1e-6)
            state[valid] = 2.0 * (values - low) / span - 1.0
        else:
            low, high = np.percentile(values, LOG_REFERENCE_PERCENTILES)
            reference = math.sqrt(float(low) * float(high))
            state[valid] = np.clip(np.log(values / reference) / log_range, -1.0, 1.0)
    return state


def relative_depth_bounds(kind: str = "affine", log_range: float = LOG_DEPTH_RANGE) -> tuple[float, float]:
    """(lowest, highest) relative depth :func:`state_to_relative_depth` can return."""
    _check_kind(kind)
    return (1.0, 2.0) if kind == "affine" else (math.exp(-log_range), math.exp(log_range))


def state_to_relative_depth(state: np.ndarray, kind: str = "affine",
                            log_range: float = LOG_DEPTH_RANGE) -> np.ndarray:
    """Relative depth (positive, affine in true depth) from a state in [-1, 1].

    "affine": ``(state + 1) / 2 + 1``, values in [1, 2], true depth up to scale and shift.
    "log": ``exp(log_range x state)``, values in [e^-c, e^c], true depth up to one scale
    (a special case of the same format: the fitted shift comes out ~0).
    """
    _check_kind(kind)
    state = np.clip(state, -1.0, 1.0)
    if kind == "affine":
        return (state + 1.0) * 0.5 + 1.0
    return np.exp(log_range * state)


def resize_masked(values: np.ndarray, weight: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Area-resize ``values`` [H, W(, C)] averaging only where ``weight`` [H, W] is 1."""
    import cv2

    weight = weight.astype(np.float32)
    values = np.nan_to_num(values.astype(np.float32))
    weighted = values * (weight[..., None] if values.ndim == 3 else weight)
    summed = cv2.resize(weighted, (width, height), interpolation=cv2.INTER_AREA)
    coverage = cv2.resize(weight, (width, height), interpolation=cv2.INTER_AREA)
    denominator = np.maximum(coverage, 1e-6)
    return summed / (denominator[..., None] if summed.ndim == 3 else denominator), coverage


def resize_valid_depth(depth: np.ndarray, valid: np.ndarray, width: int, height: int) -> np.ndarray:
    """Depth [H, W] at (width, height), averaged over ``valid`` pixels only; 0 where less than half
    a cell was valid (how targets, stereo evidence and the evaluation's maps are brought to the
    working size)."""
    small, coverage = resize_masked(depth, valid, width, height)
    return np.where(coverage > 0.5, small, 0.0).astype(np.float32)


def _rgb(image: np.ndarray) -> np.ndarray:
    return np.repeat(image[..., None], 3, axis=-1) if image.ndim == 2 else image[..., :3]


@dataclass
class SceneTriples:
    """A scene's views as triples at the working resolution (targets only when ground truth exists)."""

    names: list[str]
    image_sizes: list[tuple[int, int]]  # (width, height) of each original image
    views: np.ndarray  # [N, 9, h, w] uint8
    depth: np.ndarray | None = None  # [N, h, w] float32
    normal: np.ndarray | None = None  # [N, 3, h, w] float32
    mask: np.ndarray | None = None  # [N, h, w] bool
    sfm_depth: np.ndarray | None = None  # [N, h, w] float32, triangulated points (0 = none)
    one_centre: bool = False  # every view shot from one camera centre (a panorama: neighbours are rotations)


def centre_as_neighbours(views: "torch.Tensor", which: "torch.Tensor | None" = None) -> "torch.Tensor":
    """Triples [B, 9, h, w] with the centre view in the neighbours' places, for the triples where
    ``which`` [B] (bool) is true, all when None: what a network with ``panorama_input = "centre"``
    reads, and what ``--monocular`` trains it on."""
    import torch  # deferred: the data builder runs without torch

    alone = views[:, :3].repeat(1, 3, 1, 1)
    return alone if which is None else torch.where(which.view(-1, 1, 1, 1), alone, views)


def scene_triples(scene_dir: str | Path, working_size: int, multiple: int, *, with_targets: bool = True,
                  target_source: str = "gt", sfm_points: bool = False) -> SceneTriples:
    """Read a scene folder (images/, sparse/0, and priors/<target_source>/ for targets) into triples.

    With ``sfm_points`` the scene's images are also triangulated with their known poses
    (:func:`.baselines.triangulate_known_poses`) into ``sfm_depth`` at the working size."""
    import cv2

    from ..colmap import read_model
    from ..formats.imageio import read_image
    from ..priors import load_prior_maps

    scene_dir = Path(scene_dir)
    scene = SceneDir(scene_dir)
    model = read_model(scene_dir, use_pycolmap=False)
    images = sorted(model.images.values(), key=lambda image: image.name)
    if not images:
        raise DatasetError("the COLMAP model has no images", path=scene.model)
    centres = np.stack([image.camera_center() for image in images])
    directions = np.stack([image.rotation_matrix()[2] for image in images])  # camera z axis in the world
    neighbours = neighbour_indices(centres, directions)
    one_centre = bool(np.abs(centres - centres.mean(axis=0)).max() <= 1e-6 * max(1.0, float(np.abs(centres).max())))
    rgb_small, sizes, depth, normal, mask = [], [], [], [], []
    for image in images:
        path = scene.image(image.name)
        if not path.exists():
            raise DatasetError(f"image {image.name!r} of the COLMAP model is missing", path=path)
        rgb = _rgb(read_image(path))
        height, width = rgb.shape[:2]
        sizes.append((width, height))
        small_width, small_height = working_shape(width, height, working_size, multiple)
        rgb_small.append(cv2.resize(rgb, (small_width, small_height), interpolation=cv2.INTER_AREA))
        if with_targets:
            maps = load_prior_maps(scene_dir, target_source, image.name, size=(width, height))
            if maps.depth is None or maps.normal is None:
                raise DatasetError(f"{target_source} priors of {image.name!r} lack depth or normals",
                                   path=scene.prior(target_source))
            valid = maps.mask & (maps.depth > 0)
            small_depth, coverage = resize_masked(maps.depth, valid, small_width, small_height)
            small_normal, _ = resize_masked(maps.normal, valid, small_width, small_height)
            small_mask = coverage > 0.5
            length = np.linalg.norm(small_normal, axis=-1, keepdims=True)
            small_normal = np.where(small_mask[..., None], small_normal / np.maximum(length, 1e-6), 0.0)
            depth.append(np.where(small_mask, small_depth, 0.0).astype(np.float32))
            normal.append(small_normal.transpose(2, 0, 1).astype(np.float32))
            mask.append(small_mask)
    shapes = {array.shape for array in rgb_small}
    if len(shapes) != 1:
        raise DatasetError(f"the scene's images have different sizes {sorted(shapes)}; NDN needs one size per scene",
                           path=scene.images)
    views = np.stack([np.concatenate([rgb_small[i], rgb_small[neighbours[i, 0]], rgb_small[neighbours[i, 1]]],
                                     axis=-1).transpose(2, 0, 1) for i in range(len(images))])
    result = SceneTriples(names=[image.name for image in images], image_sizes=sizes, views=views,
                          one_centre=one_centre and len(images) > 1)
    if with_targets:
        result.depth, result.normal, result.mask = np.stack(depth), np.stack(normal), np.stack(mask)
    if sfm_points:
        from .baselines import triangulate_known_poses
        from .evidence import bin_sparse_depth

        observed = triangulate_known_poses(scene_dir)
        working = (views.shape[-1], views.shape[-2])
        result.sfm_depth = np.stack([bin_sparse_depth(observed[image.name].uv, observed[image.name].depth, size, working)
                                     for image, size in zip(images, sizes)])
    return result


def write_shard(path: str | Path, triples: SceneTriples, metadata: dict) -> None:
    """Write a scene's triples and targets as one npz shard, atomically."""
    if triples.depth is None:
        raise DatasetError("a training shard needs depth/normal targets", path=path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:
            optional = {} if triples.sfm_depth is None else {"sfm_depth": triples.sfm_depth}
            np.savez_compressed(handle, format=np.array(SHARD_FORMAT), views=triples.views, depth=triples.depth,
                                normal=triples.normal, mask=triples.mask, names=np.array(triples.names),
                                metadata=np.array(json.dumps(metadata)), **optional)


def load_shards(data_dir: str | Path, split: str = "train", *, with_scenes: bool = False,
                with_view_sky: bool = False) -> dict[str, np.ndarray]:
    """Concatenate the shards of one split: views, depth, normal, mask (see the module docstring),
    and ``sfm_depth`` when every shard has it; with ``with_scenes`` also ``scene`` [N] (str), the
    shard each triple came from (its file stem); with ``with_view_sky`` also ``view_sky``
    [N, 3, h, w] bool, the sky of each of a triple's three views, False throughout for a triple
    whose neighbours are not centres of the same shard (:func:`.sky_looks.sky_of_views`).

    Shards with different working resolutions cannot be batched together: a mix raises
    :class:`DatasetError`.
    """
    data_dir = Path(data_dir)
    paths = sorted((data_dir / "shards").glob(f"{split}_*.npz"))
    if not paths:
        raise DatasetError(f"no {split!r} shards", path=data_dir / "shards",
                           hint="build them with `esgs ndn build-data --out DIR`")
    arrays: dict[str, list[np.ndarray]] = {"views": [], "depth": [], "normal": [], "mask": []}
    scenes: list[np.ndarray] = []
    points: list[np.ndarray] = []
    view_sky: list[np.ndarray] = []
    if with_view_sky:
        from .sky_looks import sky_of_views  # imports torch: only for the runs that repaint skies
    for path in paths:
        with np.load(path, allow_pickle=False) as shard:
            if "format" not in shard or str(shard["format"]) != SHARD_FORMAT:
                raise DatasetError("not an NDN shard (missing or unknown format tag)", path=path)
            for key in arrays:
                arrays[key].append(shard[key])
            if "sfm_depth" in shard:
                points.append(shard["sfm_depth"])
            scenes.append(np.full(len(shard["views"]), path.stem))
            if with_view_sky:
                sky, known = sky_of_views(shard["views"], shard["mask"])
                view_sky.append(sky & known[:, None, None, None])
    shapes = {array.shape[-2:] for array in arrays["views"]}
    if len(shapes) != 1:
        raise DatasetError(f"shards have different working resolutions {sorted(shapes)}", path=data_dir / "shards",
                           hint="rebuild the data set with one --working-size")
    loaded = {key: np.concatenate(values) for key, values in arrays.items()}
    if len(points) == len(paths):
        loaded["sfm_depth"] = np.concatenate(points)
    if with_scenes:
        loaded["scene"] = np.concatenate(scenes)
    if with_view_sky:
        loaded["view_sky"] = np.concatenate(view_sky)
    return loaded


def plan_scenes(count: int, heldout: int, presets: tuple[str, ...] = TRAIN_PRESETS,
                heldout_presets: tuple[str, ...] = (), validation: int = 0) -> list[tuple[str, str, int]]:
    """(split, preset, seed) of every scene: training scenes cycle over ``presets`` with seeds
    1, 2, ...; validation scenes cycle over the same training presets with seeds
    ``VALIDATION_SEED_OFFSET + i``; held-out scenes use seeds >= HELDOUT_SEED_OFFSET and also
    every preset in ``heldout_presets`` (which training never sees). The three seed ranges
    never meet, so no scene is in two splits."""
    if count and 1 + (count - 1) // len(presets) >= VALIDATION_SEED_OFFSET:
        raise ConfigError(f"{count} training scenes would reach the validation seeds (>= {VALIDATION_SEED_OFFSET})")
    if validation > HELDOUT_SEED_OFFSET - VALIDATION_SEED_OFFSET:
        raise ConfigError(f"at most {HELDOUT_SEED_OFFSET - VALIDATION_SEED_OFFSET} validation scenes, got {validation}")
    plan = [("train", presets[i % len(presets)], 1 + i // len(presets)) for i in range(count)]
    plan += [("validation", presets[i % len(presets)], VALIDATION_SEED_OFFSET + i) for i in range(validation)]
    heldout_pool = tuple(presets) + tuple(heldout_presets)
    plan += [("heldout", heldout_pool[i % len(heldout_pool)], HELDOUT_SEED_OFFSET + i) for i in range(heldout)]
    return plan


def shard_scene(path: str | Path) -> tuple[str, str, int] | None:
    """(split, preset, seed) from a shard name ``<split>_<preset>_<seed>.npz``; None when the
    name does not follow that pattern (e.g. a scene added with ``esgs ndn shard``)."""
    stem = Path(path).stem
    for split in SPLITS:
        if stem.startswith(split + "_"):
            preset, _, seed = stem[len(split) + 1:].rpartition("_")
            if preset and seed.isdigit():
                return split, preset, int(seed)
    return None


def check_disjoint_splits(data_dir: str | Path, splits: tuple[str, ...] = SPLITS) -> None:
    """Raise :class:`DatasetError` when a scene (preset and seed) or a triple's images appear in
    two splits of ``DATA/shards``: a validation or held-out score would then be measured on
    data the network was trained on."""
    import hashlib

    seen_scene: dict[tuple[str, int], str] = {}
    seen_views: dict[bytes, str] = {}
    for split in splits:
        for path in sorted((Path(data_dir) / "shards").glob(f"{split}_*.npz")):
            parsed = shard_scene(path)
            if parsed is not None:
                key = (parsed[1], parsed[2])
                if key in seen_scene and seen_scene[key] != split:
                    raise DatasetError(f"scene {key[0]} seed {key[1]} is in the {seen_scene[key]!r} and the {split!r} "
                                       "splits", path=path, hint="rebuild the data with `esgs ndn build-data`")
                seen_scene[key] = split
            with np.load(path, allow_pickle=False) as shard:
                for views in shard["views"]:
                    digest = hashlib.sha1(views.tobytes()).digest()
                    if seen_views.get(digest, split) != split:
                        raise DatasetError(f"a triple of this shard is also in the {seen_views[digest]!r} split",
                                           path=path, hint="the splits must hold different scenes")
                    seen_views[digest] = split


def render_scene(preset: str, seed: int, *, views: int, width: int, height: int, samples: int, out: Path,
                 palette: str = "varied") -> Path:
    """Render one synthetic scene folder (``esgs scene``'s job, in a Blender child process)."""
    from ..terrain.scene_job import SceneJob, render_scene as render

    job = SceneJob(preset=preset, seed=seed, views=views, width=width, height=height, samples=samples,
                   palette=palette)
    return render(job, out)


def _check_resumed_palette(out_dir: Path, palette: str) -> None:
    """Refuse to add scenes of another look to a data folder (a folder from before palettes
    existed holds the fixed ``mars`` look)."""
    import json

    manifest = out_dir / "manifest.json"
    if not manifest.is_file():
        return
    built = json.loads(manifest.read_text()).get("palette", "mars")
    if built != palette:
        raise ConfigError(f"this data folder was built with --palette {built}, not {palette}", path=manifest,
                          hint=f"pass --palette {built} to continue it, or build into a new folder")


def build_dataset(out_dir: str | Path, scenes: int, *, heldout: int = 1, validation: int = 0, presets: tuple[str, ...] = TRAIN_PRESETS,
                  heldout_presets: tuple[str, ...] = (), views: int = 8, width: int = 160, height: int = 90,
                  samples: int = 8, working_size: int = 128, multiple: int = 4, keep_scenes: bool = False,
                  sfm_points: bool = True, palette: str = "varied", progress: ProgressCallback = no_progress) -> dict:
    """Render scenes with ``esgs scene`` and write one shard per scene under ``OUT/shards``.

    Resumable: a shard that already exists is skipped, so an interrupted build continues
    where it stopped. ``OUT/manifest.json`` records the plan and settings. Returns the manifest.
    """
    import shutil
    import tempfile

    NDNDataConfig(scenes=scenes, heldout=heldout, validation=validation, presets=tuple(presets), heldout_presets=tuple(heldout_presets),
                  views=views, width=width, height=height, samples=samples, working_size=working_size,
                  multiple=multiple, keep_scenes=keep_scenes, sfm_points=sfm_points, palette=palette).validate()
    out_dir = Path(out_dir)
    _check_resumed_palette(out_dir, palette)
    (out_dir / "shards").mkdir(parents=True, exist_ok=True)
    plan = plan_scenes(scenes, heldout, tuple(presets), tuple(heldout_presets), validation)
    manifest = {"format": SHARD_FORMAT, "working_size": working_size, "multiple": multiple, "views": views,
                "resolution": [width, height], "samples": samples, "sfm_points": sfm_points, "palette": palette,
                "scenes": [{"split": s, "preset": p, "seed": seed, "shard": f"shards/{s}_{p}_{seed}.npz"}
                           for s, p, seed in plan]}
    atomic_write_json(out_dir / "manifest.json", manifest)
    for index, (split, preset, seed) in enumerate(plan):
        shard = out_dir / "shards" / f"{split}_{preset}_{seed}.npz"
        progress(ProgressEvent(index, len(plan), "build-data", message=f"{preset} seed {seed}"))
        if shard.exists():
            continue
        work = Path(tempfile.mkdtemp(prefix=f".{preset}_{seed}.", dir=out_dir))
        scene_dir = work / "scene"
        try:
            try:
                render_scene(preset, seed, views=views, width=width, height=height, samples=samples, out=scene_dir,
                             palette=palette)
            except ESGSError as error:
                raise DatasetError(f"rendering scene {preset} seed {seed} failed: {error.message}",
                                   path=error.path or scene_dir, hint=error.hint) from error
            triples = scene_triples(scene_dir, working_size, multiple, sfm_points=sfm_points)
            write_shard(shard, triples, {"preset": preset, "seed": seed, "split": split})
            if keep_scenes:
                kept = out_dir / "scenes" / f"{split}_{preset}_{seed}"
                kept.parent.mkdir(parents=True, exist_ok=True)
                shutil.rmtree(kept, ignore_errors=True)
                shutil.move(str(scene_dir), str(kept))
        finally:
            shutil.rmtree(work, ignore_errors=True)
    progress(ProgressEvent(len(plan), len(plan), "build-data", kind="done"))
    return manifest
