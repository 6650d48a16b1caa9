"""NDN inference: depth and normal priors for a scene, and evaluation against ground truth.

The network works at <= 128 px on the long side. Its maps are brought back to the image
size with an image-guided filter (OpenCV's ``ximgproc.guidedFilter``: bilinear upsampling,
then edges snapped to the image's), and written to ``SCENE/priors/ndn/`` in the standard
format: depth with ``depth_kind = relative`` (affine in true depth: values in [1, 2] for the
affine depth state, true depth times one unknown scale for the log state, as the weights'
``depth_state`` says; training aligns either with ``fit_scale_shift``), unit normals in the camera frame (OpenCV
axes), and a mask of the pixels the normal branch calls surface (it was trained to output
a zero normal where there is no surface).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..progress import ProgressCallback, ProgressEvent, no_progress
from ..formats.scene_dir import SceneDir
from .data import (LOG_DEPTH_RANGE, SceneTriples, centre_as_neighbours, load_shards, relative_depth_bounds, scene_triples,
                   state_to_relative_depth)
from .diffusion import GaussianDiffusion
from .model import NDNUNet
from .checkpoint import load_checkpoint
from .config import NDNConfig

SURFACE_NORMAL_LENGTH = 0.5  # predicted normals shorter than this are "no surface"


def views_per_batch(batch_size: int, diffusion: GaussianDiffusion) -> int:
    """Views sampled per call so that one network batch holds about ``batch_size`` samples: an
    ensemble of n samples per view multiplies the batch, and large batches are slower per
    sample on a CPU (measured: 4 views x 5 samples 2.8 s/view, 1 view x 5 samples 1.8 s/view)."""
    return max(1, batch_size // max(1, diffusion.config.sample_ensemble))


def predict_states(model: NDNUNet, diffusion: GaussianDiffusion, views: torch.Tensor, *, steps: int | None = None,
                   seed: int = 0, batch_size: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """Denoise in batches: views [N, 9, h, w] in [-1, 1] -> (depth state [N, 1, h, w], normal [N, 3, h, w]).

    Batch k starts from noise seeded with ``seed + k``: the same call always gives the same maps.
    """
    depth_parts, normal_parts = [], []
    model.eval()
    batch_size = views_per_batch(batch_size, diffusion)
    for batch_index, start in enumerate(range(0, views.shape[0], batch_size)):
        depth, normal = diffusion.sample(model, views[start:start + batch_size], steps=steps, seed=seed + batch_index)
        depth_parts.append(depth)
        normal_parts.append(normal)
    return torch.cat(depth_parts), torch.cat(normal_parts)


def guided_upsample(values: np.ndarray, guide_rgb: np.ndarray, radius: int = 4, eps: float = 1e-3) -> np.ndarray:
    """Bring ``values`` [h, w] or [h, w, C] to the guide's size [H, W, 3] (uint8), edges from the guide."""
    import cv2

    height, width = guide_rgb.shape[:2]
    up = cv2.resize(values.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)
    guide = cv2.cvtColor(guide_rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    return cv2.ximgproc.guidedFilter(guide, up, radius, eps)


def maps_from_states(depth_state: np.ndarray, normal_state: np.ndarray,
                     guide_rgb: np.ndarray | None = None, *, kind: str = "affine",
                     log_range: float = LOG_DEPTH_RANGE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view's states -> (relative depth [H, W], unit normals [H, W, 3], mask [H, W] bool).

    ``depth_state`` [h, w] of kind ``kind`` (the weights' ``depth_state``, with their
    ``log_depth_range``), ``normal_state`` [3, h, w]; with ``guide_rgb`` [H, W, 3] the maps
    are upsampled to its size under its guidance, otherwise kept at the working size.
    """
    relative = state_to_relative_depth(depth_state, kind, log_range)
    if guide_rgb is not None:
        relative = np.clip(guided_upsample(relative, guide_rgb), *relative_depth_bounds(kind, log_range))
    normal, mask = unit_normals(normal_state, guide_rgb)
    return np.where(mask, relative, 0.0).astype(np.float32), np.where(mask[..., None], normal, 0.0), mask


def unit_normals(normal_state: np.ndarray, guide_rgb: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A normal state [3, h, w] -> (unit normals [H, W, 3], surface mask [H, W]): the surface is
    where the predicted normal is longer than :data:`SURFACE_NORMAL_LENGTH`; with ``guide_rgb``
    [H, W, 3] both are brought to its size (normals image-guided, the mask nearest)."""
    import cv2

    normal = normal_state.transpose(1, 2, 0)
    surface = (np.linalg.norm(normal, axis=-1) > SURFACE_NORMAL_LENGTH).astype(np.uint8)
    if guide_rgb is not None:
        height, width = guide_rgb.shape[:2]
        normal = guided_upsample(normal, guide_rgb)
        surface = cv2.resize(surface, (width, height), interpolation=cv2.INTER_NEAREST)
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    return np.where(length > 1e-6, normal / np.maximum(length, 1e-6), 0.0).astype(np.float32), surface.astype(bool)


def scene_evidence(scene_dir: str | Path, triples: SceneTriples, *,
                   stereo_source: str | None = "labels") -> tuple[np.ndarray, np.ndarray]:
    """The evidence an evidence-conditioned network reads for a scene's views, at the working size:
    (SfM depth [N, h, w] from the scene's own points as each view observes them, stereo depth
    [N, h, w] from ``priors/<stereo_source>`` where that folder exists, else zeros)."""
    from ..colmap import read_model
    from ..priors import load_prior_maps
    from ..priors.sfm import sparse_depth_map
    from .data import resize_valid_depth
    from .evidence import bin_sparse_depth

    model = read_model(scene_dir, use_pycolmap=False)
    by_name = {image.name: image for image in model.images.values()}
    count, height, width = len(triples.names), triples.views.shape[-2], triples.views.shape[-1]
    sfm = np.zeros((count, height, width), np.float32)
    stereo = np.zeros((count, height, width), np.float32)
    has_stereo = stereo_source is not None and SceneDir(scene_dir).has_prior_maps(stereo_source, "depth")
    for index, (name, size) in enumerate(zip(triples.names, triples.image_sizes)):
        sparse = sparse_depth_map(model, by_name[name].image_id)
        rows, columns = np.nonzero(sparse > 0)
        points = np.stack([columns + 0.5, rows + 0.5], axis=1)
        sfm[index] = bin_sparse_depth(points, sparse[rows, columns], (sparse.shape[1], sparse.shape[0]), (width, height))
        if has_stereo:
            labels = load_prior_maps(scene_dir, stereo_source, name, size=size)
            valid = labels.mask & (labels.depth > 0) if labels.depth is not None else np.zeros(labels.shape, bool)
            if valid.any() and not labels.relative_depth:
                stereo[index] = resize_valid_depth(labels.depth, valid, width, height)
    return sfm, stereo


@dataclass
class _ScenePrediction:
    """One network's raw output for every view of a scene, at its working size."""

    names: list[str]
    depth_states: np.ndarray  # [N, 1, h, w]
    normal_states: np.ndarray  # [N, 3, h, w]
    sky: np.ndarray | None  # [N, 1, h, w] probability, None without a sky head
    reference: torch.Tensor | None  # [N] metric reference depth of an evidence network (0: none)
    stereo: np.ndarray  # [N, h, w] the stereo labels it read (zeros without)
    config: NDNConfig
    had_stereo: bool


def _predict_scene(scene_dir: Path, weights: Path, *, steps: int | None, seed: int, batch_size: int,
                   stage: str, progress: ProgressCallback) -> _ScenePrediction:
    """Sample one network on every view of the scene (its evidence when it reads evidence)."""
    from .evidence import encode_evidence, evidence_reference

    model, diffusion, config, _ = load_checkpoint(weights)
    triples: SceneTriples = scene_triples(scene_dir, config.model.working_size, 2 ** (config.model.levels - 1),
                                          with_targets=False)
    views = torch.from_numpy(triples.views.astype(np.float32) / 127.5 - 1.0)
    if triples.one_centre and config.model.panorama_input == "centre":
        views = centre_as_neighbours(views)  # its neighbours are rotations; it was trained to read one view
    total = len(triples.names)
    log_range = config.diffusion.log_depth_range
    evidence = reference = None
    stereo = np.zeros((total, *triples.views.shape[-2:]), np.float32)
    if config.model.evidence:
        sfm, stereo = scene_evidence(scene_dir, triples)
        sfm_t, stereo_t = torch.from_numpy(sfm), torch.from_numpy(stereo)
        reference = evidence_reference(sfm_t, stereo_t)
        evidence = encode_evidence(sfm_t, stereo_t, reference, log_range)
    depth_states, normal_states, sky_maps = [], [], []
    batch_size = views_per_batch(batch_size, diffusion)
    for start in range(0, total, batch_size):
        progress(ProgressEvent(start, total, stage))
        part = slice(start, start + batch_size)
        depth, normal, sky = diffusion.sample(model, views[part], steps=steps, seed=seed + start,
                                              evidence=evidence[part] if evidence is not None else None,
                                              return_sky=True)
        depth_states.append(depth.numpy())
        normal_states.append(normal.numpy())
        sky_maps.append(sky.numpy() if sky is not None else None)
    return _ScenePrediction(
        names=list(triples.names), depth_states=np.concatenate(depth_states), normal_states=np.concatenate(normal_states),
        sky=np.concatenate(sky_maps) if sky_maps and sky_maps[0] is not None else None, reference=reference,
        stereo=stereo, config=config, had_stereo=evidence is not None and bool(evidence[:, 3].any()))


def _view_maps(prediction: _ScenePrediction, index: int,
               image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, bool]:
    """View ``index`` of a prediction at the image's size: (depth, unit normals, surface mask
    without the sky, sky mask or None, whether the depth is metric)."""
    from .evidence import depth_from_state

    config = prediction.config
    log_range = config.diffusion.log_depth_range
    state = prediction.depth_states[index, 0]
    reference = prediction.reference
    # metric where the view had evidence (its reference depth is known), else relative
    metric = bool(reference is not None and float(reference[index]) > 0)
    if metric:
        in_metres = depth_from_state(torch.from_numpy(state)[None, None], reference[index:index + 1], log_range)
        in_metres = pin_to_labels(in_metres[0, 0].numpy(), prediction.stereo[index])
        depth, normal, mask = metric_maps(in_metres, prediction.normal_states[index], image)
    else:
        depth, normal, mask = maps_from_states(state, prediction.normal_states[index], image,
                                               kind=config.diffusion.depth_state, log_range=log_range)
    sky = _sky_mask(prediction, index, image)
    if sky is not None:
        mask &= ~sky
        depth, normal = np.where(mask, depth, 0.0).astype(np.float32), np.where(mask[..., None], normal, 0.0)
    return depth, normal, mask, sky, metric


def _sky_mask(prediction: _ScenePrediction, index: int, image: np.ndarray) -> np.ndarray | None:
    """View ``index``'s sky (probability above one half) at the image's size; None without a sky head."""
    return None if prediction.sky is None else upsample_probability(prediction.sky[index, 0], image) > 0.5


def predict_sky_masks(scene_dir: str | Path, weights: str | Path, *, seed: int = 0, batch_size: int = 8,
                      progress: ProgressCallback = no_progress) -> dict[str, np.ndarray]:
    """Each view's sky mask [H, W] (bool, full image size) as one network marks it in ``esgs priors``.

    The same prediction :func:`write_ndn_priors` makes with ``weights`` (a panorama's views fed
    as the network was trained to read them, probability above one half, upsampled guided by the
    image), without writing anything: for measuring a network's sky against a reference.
    Raises :class:`~..errors.ConfigError` when the weights have no sky head.
    """
    from ..errors import ConfigError

    scene_dir = Path(scene_dir)
    prediction = _predict_scene(scene_dir, Path(weights), steps=None, seed=seed, batch_size=batch_size,
                                stage="ndn-sky", progress=progress)
    if prediction.sky is None:
        raise ConfigError(f"{weights}: these weights have no sky head; pick a network trained with one")
    return {name: _sky_mask(prediction, index, _scene_rgb(scene_dir, name))
            for index, name in enumerate(prediction.names)}


def _scene_rgb(scene_dir: Path, name: str) -> np.ndarray:
    """The scene's image ``name`` as [H, W, 3] (a grey frame repeated, alpha dropped)."""
    from ..formats.imageio import read_image

    image = read_image(SceneDir(scene_dir).image(name))
    return np.repeat(image[..., None], 3, axis=-1) if image.ndim == 2 else image[..., :3]


def write_ndn_priors(scene_dir: str | Path, weights: str | Path | None = None, *, normal_weights: str | Path | None = None,
                     steps: int | None = None, seed: int = 0, batch_size: int = 4, sky_from_normals: bool = True,
                     progress: ProgressCallback = no_progress) -> int:
    """Predict and write ``SCENE/priors/ndn/`` for every view of the scene; returns the view count.

    ``weights``: the depth network, a weights/checkpoint file or a model folder (``weights.pt``
    or latest checkpoint); ``normal_weights``: the normals network (``"same"``: the depth
    network's own). None for both means the pair shipped with the package (or the environment
    variables): :func:`.shipped.resolve_prior_networks` says which.

    The depth network writes depth, the surface mask and the sky; the normals network, where
    it sees a surface (outside its own sky), replaces the normals (docs/ndn.md: its normals
    measured better on every evaluation set, its depth did not), and with ``sky_from_normals``
    (the default) its sky is added to the sky: it marks the sky of rover views at 0.999
    precision, and training on scenes without ground truth gains from it (docs/ndn.md). Its own
    depth is written as the views' ``second_depth`` (on the same surface), which ``priors/auto``
    can blend with the depth network's in the holes of views with sky (off by default;
    docs/priors.md, "Two networks' fills in views with sky").

    Weights that read evidence get each view's SfM points and, where ``priors/labels`` exists,
    its stereo labels (:func:`scene_evidence`); their depth is then written in metres, fitted to
    the view's labels where it has some (:func:`pin_to_labels`; a view without any evidence
    stays relative). Weights with a sky head mark the sky: their pixels
    with sky probability above one half are left out of the mask and written as ``sky``.
    The headers record both networks and their content digests (``weights_sha``,
    ``normal_weights_sha``) and whether they were the package's own (``networks``).
    """
    import os
    import shutil
    import tempfile

    from ..io_utils import atomic_directory
    from ..priors import prior_dir, write_prior_maps

    from .shipped import resolve_prior_networks, weights_digest

    scene_dir = Path(scene_dir)
    networks = resolve_prior_networks(weights, normal_weights)
    depth_net = _predict_scene(scene_dir, networks.depth, steps=steps, seed=seed, batch_size=batch_size,
                               stage="ndn-infer", progress=progress)
    normal_net = None
    if networks.normals is not None:
        normal_net = _predict_scene(scene_dir, networks.normals, steps=None, seed=seed, batch_size=batch_size,
                                    stage="ndn-normals", progress=progress)
        if normal_net.names != depth_net.names:
            raise AssertionError("both networks read the scene's views in the same order")
    config = depth_net.config
    total = len(depth_net.names)
    metadata = {"method": "ndn", "weights": str(networks.depth), "weights_sha": weights_digest(networks.depth),
                "ddim_steps": str(steps or config.diffusion.sample_steps), "seed": str(seed),
                "depth_state": config.diffusion.depth_state, "networks": "default" if networks.default else "chosen"}
    if config.diffusion.depth_state == "log":
        metadata["log_depth_range"] = str(config.diffusion.log_depth_range)
    if config.model.evidence:
        metadata["evidence"] = "sfm points" + (" + stereo labels" if depth_net.had_stereo else "")
    if networks.normals is not None:
        metadata["sky_from"] = "depth and normals networks" if sky_from_normals else "depth network"
        metadata["normal_weights"] = str(networks.normals)
        metadata["normal_weights_sha"] = weights_digest(networks.normals)
        metadata["second_depth"] = "normals network"
        if normal_net.config.model.evidence:
            metadata["normal_evidence"] = "sfm points" + (" + stereo labels" if normal_net.had_stereo else "")
    # all maps go to a staging folder that replaces priors/ndn only when complete: a failure
    # never leaves a mix of old and new views
    priors = SceneDir(scene_dir).priors
    priors.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".ndn.work.", dir=priors))
    try:
        for index, name in enumerate(depth_net.names):
            image = _scene_rgb(scene_dir, name)
            depth, normal, mask, sky, metric = _view_maps(depth_net, index, image)
            if normal_net is not None:
                # one pass over its maps: normals and sky here, its depth as the second depth (below);
                # its surface is already without its own sky
                second, better, sees_surface, normal_sky, second_metric = _view_maps(normal_net, index, image)
                normal = np.where((sees_surface & mask)[..., None], better, normal).astype(np.float32)
                if sky_from_normals and normal_sky is not None:
                    sky = normal_sky if sky is None else sky | normal_sky
                    mask &= ~sky
                    depth = np.where(mask, depth, 0.0).astype(np.float32)
                    normal = np.where(mask[..., None], normal, 0.0).astype(np.float32)
                second = np.where(mask & sees_surface, second, 0.0).astype(np.float32)
            write_prior_maps(work, "ndn", name, depth=depth, normal=normal, mask=mask, relative_depth=not metric,
                             units="m" if metric else "relative", metadata=metadata, mask_kind="surface", sky=sky,
                             second_depth=second if normal_net is not None else None,
                             second_relative_depth=normal_net is not None and not second_metric)
        with atomic_directory(prior_dir(scene_dir, "ndn"), overwrite=True) as staging:
            os.replace(prior_dir(work, "ndn"), staging)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    progress(ProgressEvent(total, total, "ndn-infer", kind="done"))
    return total


def ndn_priors_header(scene_dir: str | Path) -> dict[str, str]:
    """The header of the scene's first ``priors/ndn`` depth map (what :func:`write_ndn_priors`
    records: the networks, their digests, the sampling); empty when there is none or it cannot
    be read."""
    from ..formats.imageio import read_depth_exr

    folder = SceneDir(scene_dir).prior_maps("ndn", "depth")
    maps = sorted(folder.glob("*.exr")) if folder.is_dir() else []
    try:
        return dict(read_depth_exr(maps[0])[1]) if maps else {}
    except Exception:  # noqa: BLE001 - provenance only: an unreadable header reads as unknown
        return {}


def made_by_package(header: dict[str, str]) -> bool:
    """Whether ``priors/ndn`` with this header (:func:`ndn_priors_header`) came from the package's
    own networks: recorded as such, or (folders from before the record) the shipped depth network
    named as the weights and no normals network."""
    from .shipped import SHIPPED_WEIGHTS

    if "networks" in header:
        return header["networks"] == "default"
    return bool(header.get("weights")) and "normal_weights" not in header \
        and Path(header["weights"]).resolve() == SHIPPED_WEIGHTS.resolve()


def outdated_ndn_priors(scene_dir: str | Path) -> str | None:
    """Why the scene's ``priors/ndn`` should be predicted again, or None to keep them.

    Only priors the package's own networks made are judged (a user's chosen weights are kept):
    they are outdated when the package's networks have changed since (another digest, or a
    folder from before the normals network shipped), or when the normals network read no
    stereo labels and the scene has them now. (A folder from before the normals network's depth
    was kept as the second depth is kept: only the opt-in blend reads it.) Nothing is outdated
    while the environment names other weights."""
    from ..errors import CheckpointError
    from .shipped import resolve_prior_networks, weights_digest

    header = ndn_priors_header(scene_dir)
    if not header:
        return None
    try:
        networks = resolve_prior_networks()
    except CheckpointError:
        return None  # the package lacks a network: predicting again could not do better
    if not networks.default:
        return None
    if not made_by_package(header):
        return None
    expected = {"weights_sha": weights_digest(networks.depth),
                "normal_weights_sha": weights_digest(networks.normals) if networks.normals else None,
                "sky_from": "depth and normals networks" if networks.normals else None}
    if any(header.get(key) != value for key, value in expected.items() if key != "sky_from"):
        return "the package's NDN weights changed since they were predicted"
    if header.get("sky_from") != expected["sky_from"]:
        return "the package's normals network marks the sky now"
    # the normals network reads the stereo labels when they exist (what was measured): priors
    # predicted before the labels were made are predicted again once they are
    if header.get("normal_evidence") == "sfm points" and SceneDir(scene_dir).has_prior_maps("labels", "depth"):
        return "stereo labels exist now, which the normals network reads"
    return None


def pin_to_labels(depth: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """A completion's metric depth [h, w] fitted to the view's stereo labels [h, w] (0 = none) by
    the trainer's robust scale and shift (``priors.pinning.pin_relative_depth``), so the pixels it
    fills continue the labels; unchanged with too few labels or a fit that is not positive.

    Why: the network's own scale is less accurate than its shape (held-out AbsRel 0.077 unaligned
    against 0.052 aligned), and labels-then-pinned-completion measured best of the fusions
    (docs/ndn.md, the ``fused_pinned`` row)."""
    from ..priors.pinning import pin_relative_depth

    pinned = pin_relative_depth(depth, np.ones(depth.shape, bool), labels)
    return depth if pinned is None else np.where(pinned > 0, pinned, depth).astype(np.float32)


def upsample_probability(probability: np.ndarray, guide_rgb: np.ndarray) -> np.ndarray:
    """A [h, w] probability map at the guide's size (image-guided, clipped to [0, 1])."""
    return np.clip(guided_upsample(probability, guide_rgb), 0.0, 1.0)


def metric_maps(depth: np.ndarray, normal_state: np.ndarray,
                guide_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view's metric depth [h, w] and normal state [3, h, w] -> (depth [H, W] in metres,
    unit normals [H, W, 3], surface mask [H, W]) at the guide's size, as :func:`maps_from_states`."""
    normal, surface = unit_normals(normal_state, guide_rgb)
    # depth is up-sampled in log space: a guided filter's averages must not mix near and far linearly
    depth = np.exp(guided_upsample(np.log(np.maximum(depth, 1e-6)), guide_rgb))
    return np.where(surface, depth, 0.0).astype(np.float32), np.where(surface[..., None], normal, 0.0), surface


def depth_metrics(relative: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> dict[str, float]:
    """AbsRel and delta1 of a relative depth [H, W] against metric ``truth`` [H, W] after the
    robust scale/shift fit over ``mask`` [H, W] bool (the same alignment training uses)."""
    from ..priors.losses import fit_scale_shift

    valid = mask & (truth > 0)
    scale, shift = fit_scale_shift(relative, truth, valid)
    aligned = (scale * relative + shift)[valid].clamp_min(1e-6)
    target = truth[valid]
    ratio = torch.maximum(aligned / target, target / aligned)
    return {"abs_rel": float(((aligned - target).abs() / target).mean()), "delta1": float((ratio < 1.25).float().mean())}


def normal_metrics(predicted: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> dict[str, float]:
    """Mean angular error (degrees) and fraction under 11.25 deg: [3, H, W] normals, [H, W] mask."""
    unit = predicted / predicted.norm(dim=0, keepdim=True).clamp_min(1e-6)
    cosine = (unit * truth).sum(dim=0).clamp(-1.0, 1.0)[mask]
    angle = torch.rad2deg(torch.arccos(cosine))
    return {"normal_mean_deg": float(angle.mean()), "normal_within_11_25": float((angle < 11.25).float().mean())}


def score_view(relative: np.ndarray, normal: np.ndarray, truth_depth: np.ndarray, truth_normal: np.ndarray,
               mask: np.ndarray) -> dict[str, float]:
    """All scores of one view: ``relative`` [h, w] depth known up to scale and shift (or metric),
    ``normal`` [3, h, w], truth depth [h, w] (metres), truth normals [3, h, w], mask [h, w] bool.

    Depth is aligned with ``fit_scale_shift`` before AbsRel/delta1; baselines use this too.
    """
    mask_tensor = torch.from_numpy(np.asarray(mask, bool))
    return {**depth_metrics(torch.from_numpy(np.asarray(relative, np.float32)),
                            torch.from_numpy(np.asarray(truth_depth, np.float32)), mask_tensor),
            **normal_metrics(torch.from_numpy(np.asarray(normal, np.float32)),
                             torch.from_numpy(np.asarray(truth_normal, np.float32)), mask_tensor)}


def mean_scores(per_view: list[dict[str, float]]) -> dict[str, float]:
    """Means over views of every score in ``per_view`` (a score some views lack, such as the sky
    IoU of views without sky, is the mean over the views that have it)."""
    keys: list[str] = []
    for scores in per_view:
        keys += [key for key in scores if key not in keys]
    return {key: float(np.mean([scores[key] for scores in per_view if key in scores])) for key in keys}


def sky_iou(sky_probability: np.ndarray, surface: np.ndarray) -> float | None:
    """IoU of the predicted sky (probability > 0.5) with the true one (no surface); None when
    neither has a sky pixel (a view without sky says nothing about it)."""
    predicted, truth = np.asarray(sky_probability) > 0.5, ~np.asarray(surface, bool)
    union = int((predicted | truth).sum())
    return None if union == 0 else float((predicted & truth).sum() / union)


def arrays_evidence(arrays: dict[str, np.ndarray], index: int, mode: str,
                    log_range: float) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The evidence of triple ``index`` for ``mode`` (:data:`.evidence.EVIDENCE_MODES`): SfM from
    ``sfm_depth``, stereo from ``stereo_depth`` (real labels added to the arrays by the caller).
    Returns (evidence [1, 4, h, w], reference [1]), or (None, None) for no evidence."""
    from ..errors import DatasetError
    from .evidence import EVIDENCE_MODES, encode_evidence, evidence_reference

    if mode not in EVIDENCE_MODES:
        raise ValueError(f"evidence mode must be one of {EVIDENCE_MODES}, got {mode!r}")
    if mode == "none":
        return None, None
    shape = arrays["depth"][index].shape
    maps = {}
    for key, wanted in (("sfm_depth", "sfm" in mode), ("stereo_depth", "stereo" in mode)):
        if wanted and key not in arrays:
            raise DatasetError(f"evidence mode {mode!r} needs {key!r} in the data, which has none",
                               hint="shards get sfm_depth from `esgs ndn shard`/`build-data`; stereo comes from labels")
        maps[key] = torch.from_numpy(np.asarray(arrays[key][index], np.float32))[None] if wanted \
            else torch.zeros((1, *shape))
    reference = evidence_reference(maps["sfm_depth"], maps["stereo_depth"])
    if float(reference[0]) <= 0:
        return None, None
    return encode_evidence(maps["sfm_depth"], maps["stereo_depth"], reference, log_range), reference


def scores_by_scene(per_view: list[dict[str, float]], scenes) -> dict[str, dict[str, float]]:
    """Per scene (in order of first appearance), its ``views`` count and the means of its views'
    scores: ``per_view`` as :func:`evaluate_arrays` returns it, ``scenes`` [N] the scene of each."""
    grouped: dict[str, list[dict[str, float]]] = {}
    for scores, scene in zip(per_view, scenes):
        grouped.setdefault(str(scene), []).append(scores)
    return {scene: {"views": len(members), **mean_scores(members)} for scene, members in grouped.items()}


def predict_triple(model: NDNUNet, diffusion: GaussianDiffusion, arrays: dict[str, np.ndarray], index: int, *,
                   steps: int | None = None, seed: int = 0, ensemble: int | None = None,
                   evidence_mode: str = "none") -> tuple[np.ndarray, np.ndarray, np.ndarray | None, bool]:
    """One triple of ``arrays`` sampled from noise seeded with ``seed``: (depth [h, w], normals
    [3, h, w], sky probability [h, w] or None, whether the depth is metric). A network that reads
    evidence gets the triple's ``evidence_mode`` evidence (:func:`arrays_evidence`) and its depth
    is then in metres; otherwise it is relative (the weights' depth state)."""
    from .evidence import depth_from_state

    log_range = diffusion.config.log_depth_range
    views = torch.from_numpy(arrays["views"][index:index + 1].astype(np.float32) / 127.5 - 1.0)
    evidence, reference = arrays_evidence(arrays, index, evidence_mode, log_range) \
        if model.config.evidence else (None, None)
    state, normal, sky = diffusion.sample(model, views, steps=steps, seed=seed, ensemble=ensemble,
                                          evidence=evidence, return_sky=True)
    if reference is not None:
        depth = depth_from_state(state, reference, log_range)[0, 0].numpy()
    else:
        depth = state_to_relative_depth(state[0, 0].numpy(), diffusion.config.depth_state, log_range)
    return depth, normal[0].numpy(), (sky[0, 0].numpy() if sky is not None else None), reference is not None


def score_triple(depth: np.ndarray, normal: np.ndarray, sky: np.ndarray | None, metric: bool,
                 arrays: dict[str, np.ndarray], index: int) -> dict[str, float]:
    """Every score of one prediction (:func:`predict_triple`) against triple ``index``'s truth:
    :func:`score_view`, the unaligned ``abs_rel_metric``/``delta1_metric`` of a metric depth and
    ``sky_iou`` where the prediction or the truth has sky."""
    truth = (arrays["depth"][index], arrays["normal"][index], arrays["mask"][index])
    scores = score_view(depth, normal, *truth)
    if metric:
        scores.update(metric_depth_scores(depth, truth[0], truth[2]))
    if sky is not None:
        iou = sky_iou(sky, truth[2])
        if iou is not None:
            scores["sky_iou"] = iou
    return scores


def evaluate_arrays(model: NDNUNet, diffusion: GaussianDiffusion, arrays: dict[str, np.ndarray], *,
                    steps: int | None = None, seed: int = 0, ensemble: int | None = None,
                    evidence_mode: str = "none", progress: ProgressCallback = no_progress) -> list[dict[str, float]]:
    """Scores of every triple in ``arrays`` (views, depth, normal, mask as in a shard); triple
    ``i`` is sampled alone from noise seeded with ``seed + i`` (``ensemble`` samples of it
    when given, else the model's ``sample_ensemble``); states are read as the diffusion
    config's ``depth_state``. Returns one dict per triple (:func:`score_triple`); a network that
    reads evidence gets ``evidence_mode`` evidence (:func:`predict_triple`)."""
    count = arrays["views"].shape[0]
    per_view = []
    for index in range(count):
        progress(ProgressEvent(index, count, "ndn-eval"))
        prediction = predict_triple(model, diffusion, arrays, index, steps=steps, seed=seed + index,
                                    ensemble=ensemble, evidence_mode=evidence_mode)
        per_view.append(score_triple(*prediction, arrays, index))
    progress(ProgressEvent(count, count, "ndn-eval", kind="done"))
    return per_view


def metric_depth_scores(depth: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """AbsRel and delta1 of a metric depth [h, w] against the truth over ``mask``, unaligned."""
    valid = np.asarray(mask, bool) & (truth > 0)
    predicted = np.maximum(np.asarray(depth, np.float64)[valid], 1e-6)
    target = np.asarray(truth, np.float64)[valid]
    ratio = np.maximum(predicted / target, target / predicted)
    return {"abs_rel_metric": float(np.mean(np.abs(predicted - target) / target)),
            "delta1_metric": float(np.mean(ratio < 1.25))}


def evaluate_ndn(weights: str | Path, data_dir: str | Path, *, split: str = "heldout", steps: int | None = None,
                 seed: int = 0, limit: int = 0, ensemble: int | None = None, reduce: str | None = None,
                 evidence_mode: str = "sfm", progress: ProgressCallback = no_progress) -> dict:
    """Scores on a data split: mean AbsRel and delta1 (depth after scale/shift alignment),
    normal mean angular error and the fraction within 11.25 deg, over surface pixels, and the
    same means per scene (``per_scene``: shard stem -> scores, with its ``views`` count).
    ``steps``, ``ensemble`` and ``reduce`` override the model's sampling settings; an
    evidence-conditioned network reads ``evidence_mode`` evidence (:func:`arrays_evidence`)."""
    model, diffusion, config, _ = load_checkpoint(weights)
    if reduce:
        diffusion.config.sample_reduce = reduce
        diffusion.config.validate()
    arrays = load_shards(data_dir, split, with_scenes=True)
    if limit:
        arrays = {key: value[:limit] for key, value in arrays.items()}
    scenes = arrays.pop("scene")
    evidence_mode = evidence_mode if config.model.evidence else "none"
    per_view = evaluate_arrays(model, diffusion, arrays, steps=steps, seed=seed, ensemble=ensemble,
                               evidence_mode=evidence_mode, progress=progress)
    return {"split": split, "evidence": evidence_mode, "views": len(per_view), "ddim_steps": steps or diffusion.config.sample_steps,
            "ensemble": ensemble or diffusion.config.sample_ensemble, "reduce": diffusion.config.sample_reduce,
            **mean_scores(per_view), "per_scene": scores_by_scene(per_view, scenes)}
