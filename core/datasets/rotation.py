"""Rotation-only camera stations: rotations and one shared focal length from feature matches.

Frames taken by one camera turning about (nearly) one point — a rover mast pan/tilt
sequence, a tripod panorama — have no parallax, so SfM cannot triangulate them. Their
geometry is fully described by one intrinsic matrix K and one rotation per frame: a pixel
``x_i`` of frame i and its match ``x_j`` in frame j satisfy ``x_j ~ K R_j R_i^T K^-1 x_i``.

Pipeline: OpenCV SIFT features (saturated pixels masked), ratio-test matches for every pair,
a RANSAC homography per pair (``H_ij = K R_j R_i^T K^-1``), initial rotations chained along a
maximum spanning tree of the match graph, then a robust bundle adjustment of all rotations
and the focal length (Levenberg-Marquardt, analytic Jacobian) on the symmetric transfer error. The mosaic
reprojection error reported is that transfer error, in pixels, over the matches kept.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..colmap.model import Camera
from ..errors import ConfigError, DatasetError
from ..progress import ProgressCallback, ProgressEvent, no_progress
from ..formats.scene_dir import SceneDir
from .common import check_readable, list_images, scene_provenance, station_model


@dataclass
class RotationOnlyOptions:
    """Settings of the rotation-only station estimate."""

    focal_px: float | None = field(default=None, metadata={"help": "rough focal length in pixels; the search for the initial value spans 0.7-1.4x of it (default: a wide search)"})
    refine_focal: bool = field(default=True, metadata={"help": "refine the shared focal length in the adjustment"})
    refine_principal_point: bool = field(default=False, metadata={"help": "also refine the principal point (default: image centre)"})
    max_features: int = field(default=3000, metadata={"help": "SIFT features per image"})
    ratio: float = field(default=0.8, metadata={"help": "Lowe ratio test threshold"})
    ransac_px: float = field(default=3.0, metadata={"help": "RANSAC homography threshold, pixels"})
    min_inliers: int = field(default=25, metadata={"help": "homography inliers needed to link two frames"})
    outlier_px: float = field(default=2.0, metadata={"help": "after adjustment, drop matches with a larger transfer error and adjust again"})
    saturation_dn: int = field(default=250, metadata={"help": "mask pixels at or above this value (and around them) for features"})
    overwrite: bool = field(default=False, metadata={"help": "replace an existing output folder"})

    def validate(self) -> None:
        if self.focal_px is not None and not self.focal_px > 0:
            raise ConfigError(f"focal_px must be positive, got {self.focal_px}")
        if not 0.3 <= self.ratio <= 1.0:
            raise ConfigError(f"ratio {self.ratio} must be in [0.3, 1]")
        if self.min_inliers < 8:
            raise ConfigError(f"min_inliers {self.min_inliers} must be at least 8")


def _features(gray: np.ndarray, options: RotationOnlyOptions):
    import cv2

    mask = (gray < options.saturation_dn).astype(np.uint8) * 255
    # Features on the rim of a saturated region move with the exposure, not the scene.
    mask = cv2.erode(mask, np.ones((7, 7), np.uint8))
    sift = cv2.SIFT_create(nfeatures=options.max_features)
    keypoints, descriptors = sift.detectAndCompute(gray, mask)
    points = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2)
    return points, descriptors


def _match_pair(desc_a, desc_b, ratio: float) -> np.ndarray:
    """[M, 2] index pairs passing the ratio test in both directions (mutual nearest neighbours)."""
    if desc_a is None or desc_b is None or len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    a, b = desc_a.astype(np.float32), desc_b.astype(np.float32)
    # Squared distances through one matrix product: much faster than a per-query matcher loop.
    distances = np.maximum((a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T, 0.0)

    def passing(d: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
        best = np.argmin(d, axis=axis)
        first = np.take_along_axis(d, np.expand_dims(best, axis), axis).squeeze(axis)
        np.put_along_axis(d, np.expand_dims(best, axis), np.inf, axis)
        second = d.min(axis=axis)
        np.put_along_axis(d, np.expand_dims(best, axis), first[:, None] if axis == 1 else first[None, :], axis)
        return best, first < (ratio * ratio) * second  # squared distances

    forward, forward_ok = passing(distances, 1)
    backward, backward_ok = passing(distances, 0)
    rows = np.arange(len(a))
    mutual = forward_ok & backward_ok[forward] & (backward[forward] == rows)
    return np.stack([rows[mutual], forward[mutual]], axis=1).astype(np.int64)


def _nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(matrix)
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:
        rotation = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return rotation


def _intrinsics(focal: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])


def _inverse_intrinsics(K: np.ndarray) -> np.ndarray:
    """Closed-form inverse of a zero-skew intrinsic matrix (np.linalg.inv is slow for many tiny calls)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.array([[1.0 / fx, 0.0, -cx / fx], [0.0, 1.0 / fy, -cy / fy], [0.0, 0.0, 1.0]])


def focal_from_homographies(homographies: list[np.ndarray], weights: list[float], cx: float, cy: float, low: float, high: float) -> float:
    """The focal length (pixels) that makes ``K^-1 H K`` most nearly a rotation for all pairs.

    Each inter-frame homography of a rotating camera is ``K R K^-1``; with the wrong focal
    length ``K^-1 H K`` is not orthogonal. A log-spaced search over [low, high] picks the
    focal length with the smallest weighted median of ``|M M^T - I|`` (M scaled to det 1).
    """
    candidates = np.geomspace(low, high, 241)
    weights_array = np.asarray(weights, dtype=np.float64)
    scores = []
    for focal in candidates:
        K = _intrinsics(focal, cx, cy)
        K_inv = _inverse_intrinsics(K)
        errors = []
        for homography in homographies:
            M = K_inv @ homography @ K
            determinant = np.linalg.det(M)
            M = M / np.cbrt(determinant) if determinant != 0 else M
            errors.append(np.linalg.norm(M @ M.T - np.eye(3)))
        errors = np.asarray(errors)
        order = np.argsort(errors)
        cumulative = np.cumsum(weights_array[order])
        scores.append(errors[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])
    return float(candidates[int(np.argmin(scores))])


def _transfer(rot_i: np.ndarray, rot_j: np.ndarray, K: np.ndarray, points_i: np.ndarray) -> np.ndarray:
    """Pixels [M, 2] of frame i moved into frame j through the two world-to-camera rotations."""
    rays = _inverse_intrinsics(K) @ np.c_[points_i, np.ones(len(points_i))].T  # [3, M] camera i
    projected = K @ (rot_j @ (rot_i.T @ rays))
    return (projected[:2] / projected[2:]).T


def _skew(vectors: np.ndarray) -> np.ndarray:
    """[M, 3] -> [M, 3, 3] cross-product matrices."""
    out = np.zeros(vectors.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -vectors[..., 2], vectors[..., 1]
    out[..., 1, 0], out[..., 1, 2] = vectors[..., 2], -vectors[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -vectors[..., 1], vectors[..., 0]
    return out


def _station_residuals(rotations, free, flat, intrinsics, refine_focal, refine_principal_point, jacobian):
    """Transfer residuals [2 * M, 2] (matches i->j, then j->i) and optionally their Jacobian [2 * M, 2, P].

    Parameters P: a rotation correction (3) per free image, applied on the left
    (``R <- exp(w) R``), then the focal length and the principal point when refined.
    """
    focal, cx, cy = intrinsics
    first, second, points_first, points_second = flat
    keys = sorted(rotations)
    index = {key: k for k, key in enumerate(keys)}
    table = np.stack([rotations[key] for key in keys])
    column = np.full(len(keys), -1)
    for position, image in enumerate(free):
        column[index[image]] = 3 * position
    n_rot = 3 * len(free)
    n_params = n_rot + (1 if refine_focal else 0) + (2 if refine_principal_point else 0)
    residual_parts, jacobian_parts = [], []
    for source, target, source_points, target_points in ((first, second, points_first, points_second), (second, first, points_second, points_first)):
        source_index = np.array([index[k] for k in source.tolist()], dtype=np.int64) if len(source) else np.zeros(0, np.int64)
        target_index = np.array([index[k] for k in target.tolist()], dtype=np.int64) if len(target) else np.zeros(0, np.int64)
        rotation_source, rotation_target = table[source_index], table[target_index]
        rays = np.stack([(source_points[:, 0] - cx) / focal, (source_points[:, 1] - cy) / focal, np.ones(len(source_points))], axis=1)
        relative = np.einsum("mij,mkj->mik", rotation_target, rotation_source)  # R_target R_source^T
        moved = np.einsum("mij,mj->mi", relative, rays)
        depth = moved[:, 2]
        projected = focal * moved[:, :2] / depth[:, None] + np.array([cx, cy])
        residual_parts.append(projected - target_points)
        if not jacobian:
            continue
        count = len(source_points)
        d_projection = np.zeros((count, 2, 3))  # d projected / d moved
        d_projection[:, 0, 0] = d_projection[:, 1, 1] = focal / depth
        d_projection[:, 0, 2] = -focal * moved[:, 0] / depth**2
        d_projection[:, 1, 2] = -focal * moved[:, 1] / depth**2
        block = np.zeros((count, 2, n_params + 3))  # 3 spare columns absorb the fixed root image
        rows = np.arange(count)[:, None, None]
        coordinates = np.arange(2)[None, :, None]
        # Target rotation exp(w) R: d moved = -[moved]x w.
        target_columns = np.where(column[target_index] >= 0, column[target_index], n_params)
        block[rows, coordinates, target_columns[:, None, None] + np.arange(3)] += -d_projection @ _skew(moved)
        # Source rotation: R_source^T = R^T exp(-w), so d moved = R_target R_source^T [ray]x w.
        source_columns = np.where(column[source_index] >= 0, column[source_index], n_params)
        block[rows, coordinates, source_columns[:, None, None] + np.arange(3)] += d_projection @ relative @ _skew(rays)
        through_rays = np.einsum("mij,mjk->mik", d_projection, relative)  # d projected / d ray
        next_column = n_rot
        if refine_focal:
            d_ray = np.stack([-(source_points[:, 0] - cx) / focal**2, -(source_points[:, 1] - cy) / focal**2, np.zeros(count)], axis=1)
            block[:, :, next_column] = moved[:, :2] / depth[:, None] + np.einsum("mij,mj->mi", through_rays, d_ray)
            next_column += 1
        if refine_principal_point:
            block[:, 0, next_column] += 1.0
            block[:, 1, next_column + 1] += 1.0
            block[:, :, next_column] += -through_rays[:, :, 0] / focal
            block[:, :, next_column + 1] += -through_rays[:, :, 1] / focal
        jacobian_parts.append(block[:, :, :n_params])
    residuals = np.concatenate(residual_parts)
    return residuals, (np.concatenate(jacobian_parts) if jacobian else None)


def station_errors(rotations: dict[int, np.ndarray], intrinsics: tuple[float, float, float], flat) -> np.ndarray:
    """[2 * M] transfer errors (pixels) of every match, i->j then j->i."""
    residuals, _ = _station_residuals(rotations, [], flat, intrinsics, False, False, False)
    return np.linalg.norm(residuals, axis=1)


def _huber(errors: np.ndarray, scale: float) -> float:
    return float(np.where(errors <= scale, 0.5 * errors**2, scale * (errors - 0.5 * scale)).sum())


def adjust_station(
    rotations: dict[int, np.ndarray],
    free: list[int],
    flat,
    intrinsics: tuple[float, float, float],
    *,
    refine_focal: bool = True,
    refine_principal_point: bool = False,
    huber_px: float = 1.0,
    iterations: int = 100,
) -> tuple[dict[int, np.ndarray], tuple[float, float, float], float]:
    """Levenberg-Marquardt on the robust (Huber) symmetric transfer error, analytic Jacobian.

    rotations: {image: [3, 3] world-to-camera}; only ``free`` images move. flat: (first [M],
    second [M], pixels in first [M, 2], pixels in second [M, 2]). intrinsics: (focal, cx, cy).
    Rotations are updated on the left by small rotation vectors, re-linearised every step.
    Returns the new rotations, intrinsics and final robust cost.
    """
    from scipy.spatial.transform import Rotation

    def cost_of(rots, intr):
        return _huber(station_errors(rots, intr, flat), huber_px)

    cost = cost_of(rotations, intrinsics)
    damping = 1e-3
    for _ in range(iterations):
        residuals, jacobian = _station_residuals(rotations, free, flat, intrinsics, refine_focal, refine_principal_point, True)
        errors = np.linalg.norm(residuals, axis=1)
        weights = np.where(errors <= huber_px, 1.0, huber_px / np.maximum(errors, 1e-12))  # IRLS form of Huber
        J = jacobian.reshape(-1, jacobian.shape[-1])
        w = np.repeat(weights, 2)
        normal = J.T @ (J * w[:, None])
        gradient = J.T @ (w * residuals.ravel())
        improved = False
        while damping < 1e8:
            step = np.linalg.solve(normal + damping * np.diag(np.diag(normal) + 1e-12), -gradient)
            candidate = dict(rotations)
            for position, image in enumerate(free):
                candidate[image] = Rotation.from_rotvec(step[3 * position : 3 * position + 3]).as_matrix() @ rotations[image]
            tail = step[3 * len(free) :]
            focal, cx, cy = intrinsics
            if refine_focal:
                focal, tail = focal + tail[0], tail[1:]
            if refine_principal_point:
                cx, cy = cx + tail[0], cy + tail[1]
            new_cost = cost_of(candidate, (focal, cx, cy))
            if new_cost < cost:
                improved = cost - new_cost > 1e-10 * cost
                rotations, intrinsics, cost = candidate, (focal, cx, cy), new_cost
                damping = max(damping / 3.0, 1e-9)
                break
            damping *= 4.0
        if not improved:
            break
    return rotations, intrinsics, cost


def estimate_rotations(
    images: list[np.ndarray],
    options: RotationOnlyOptions | None = None,
    progress: ProgressCallback = no_progress,
) -> dict[str, Any]:
    """Rotations and a shared pinhole camera for frames taken from one centre.

    images: N grey [H, W] or RGB [H, W, 3] uint8 arrays of one size (pixel coordinates as
    COLMAP: the top-left pixel's centre at (0.5, 0.5)).
    Returns plain data: ``registered`` (frame indices in the largest linked group),
    ``rotations`` ({index: [3, 3] world-to-camera}, the first registered frame = identity),
    ``focal_px``, ``principal_point``, the error figures (``mean_error_px``, ``median_error_px``,
    ``rms_error_px`` over the kept matches; ``kept_fraction``), ``pairs`` (linked pairs).
    """
    import cv2

    options = options or RotationOnlyOptions()
    options.validate()
    if len(images) < 2:
        raise DatasetError(f"a rotation-only station needs at least 2 frames, got {len(images)}")
    height, width = images[0].shape[:2]
    if any(image.shape[:2] != (height, width) for image in images):
        raise DatasetError("frames of a rotation-only station must all have the same size", hint="resize or split them")
    grays = [cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image for image in images]
    features = []
    for index, gray in enumerate(grays):
        features.append(_features(gray, options))
        progress(ProgressEvent(index + 1, len(grays), stage="features"))

    # OpenCV keypoints use the pixel-centre-at-0 convention; COLMAP's is 0.5.
    points = [p + 0.5 for p, _ in features]
    count = len(images)
    links: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    all_pairs = [(i, j) for i in range(count) for j in range(i + 1, count)]
    for step, (i, j) in enumerate(all_pairs):
        matches = _match_pair(features[i][1], features[j][1], options.ratio)
        if len(matches) >= options.min_inliers:
            a, b = points[i][matches[:, 0]], points[j][matches[:, 1]]
            homography, inliers = cv2.findHomography(a, b, cv2.RANSAC, options.ransac_px, maxIters=4000, confidence=0.999)
            if homography is not None and int(inliers.sum()) >= options.min_inliers:
                keep = inliers.ravel().astype(bool)
                links[(i, j)] = (a[keep], b[keep], homography)
        if j == count - 1:  # one event per row of pairs keeps the console quiet
            progress(ProgressEvent(step + 1, len(all_pairs), stage="match"))
    if not links:
        raise DatasetError(
            "no two frames share enough matched features to be linked",
            hint="frames must overlap (30 % or more); try a lower --min-inliers or check the images",
        )

    # Largest connected group, initial rotations along a maximum spanning tree (Prim).
    weight = {pair: len(link[0]) for pair, link in links.items()}
    neighbours: dict[int, list[int]] = {k: [] for k in range(count)}
    for i, j in links:
        neighbours[i].append(j)
        neighbours[j].append(i)
    seen, groups = set(), []
    for start in range(count):
        if start in seen:
            continue
        group, stack = [], [start]
        seen.add(start)
        while stack:
            node = stack.pop()
            group.append(node)
            for other in neighbours[node]:
                if other not in seen:
                    seen.add(other)
                    stack.append(other)
        groups.append(sorted(group))
    registered = max(groups, key=len)
    if len(registered) < 2:
        raise DatasetError("no two frames could be linked by a homography", hint="check overlap and image content")

    cx, cy = width / 2.0, height / 2.0
    # The spanning tree's rotations need a focal length close to the truth: search it around
    # the given value (or over a wide range) with the homographies of the linked pairs.
    in_group = [pair for pair in links if pair[0] in registered]
    guess = float(options.focal_px or width)
    low, high = (0.7 * guess, 1.4 * guess) if options.focal_px else (0.25 * width, 6.0 * width)
    focal = guess
    if options.refine_focal:
        focal = focal_from_homographies([links[p][2] for p in in_group], [weight[p] for p in in_group], cx, cy, low, high)
    K = _intrinsics(focal, cx, cy)
    K_inv = _inverse_intrinsics(K)
    root = registered[0]
    rotations = {root: np.eye(3)}
    while len(rotations) < len(registered):
        best = None
        for (i, j), w in weight.items():
            if (i in rotations) != (j in rotations) and (best is None or w > best[1]):
                best = ((i, j), w)
        (i, j), _ = best
        relative = _nearest_rotation(K_inv @ links[(i, j)][2] @ K)  # R_j R_i^T
        if i in rotations:
            rotations[j] = relative @ rotations[i]
        else:
            rotations[i] = relative.T @ rotations[j]

    pairs = [pair for pair in links if pair[0] in rotations]
    free = [image for image in registered if image != root]  # the root fixes the world frame
    order = {image: position for position, image in enumerate(registered)}
    free = [image for image in registered if image != root]  # the root fixes the world frame
    data = {pair: (links[pair][0], links[pair][1]) for pair in pairs}
    total_matches = sum(len(a) for a, _ in data.values())
    flat = (
        np.concatenate([np.full(len(a), i) for (i, _), (a, _) in data.items()]),
        np.concatenate([np.full(len(a), j) for (_, j), (a, _) in data.items()]),
        np.concatenate([a for a, _ in data.values()]),
        np.concatenate([b for _, b in data.values()]),
    )
    intrinsics = (focal, cx, cy)
    for round_index in range(3):
        rotations, intrinsics, cost = adjust_station(
            rotations, free, flat, intrinsics, refine_focal=options.refine_focal, refine_principal_point=options.refine_principal_point
        )
        progress(ProgressEvent(round_index + 1, 3, stage="adjust", metrics={"cost": cost}))
        error = station_errors(rotations, intrinsics, flat).reshape(2, -1).mean(axis=0)
        if round_index == 0:
            all_errors = error
        good = error <= options.outlier_px
        if good.all():
            break
        flat = tuple(array[good] for array in flat)

    rots = rotations
    K_now = _intrinsics(*intrinsics)
    errors = station_errors(rotations, intrinsics, flat)
    kept_pairs = len(set(zip(flat[0].tolist(), flat[1].tolist())))
    return {
        "registered": registered,
        "unregistered": [k for k in range(count) if k not in order],
        "rotations": rots,
        "focal_px": float(K_now[0, 0]),
        "principal_point": [float(K_now[0, 2]), float(K_now[1, 2])],
        "image_size": [int(width), int(height)],
        "pairs": kept_pairs,
        "matches": int(len(flat[0])),
        "kept_fraction": float(len(flat[0]) / max(total_matches, 1)),
        "first_pass_median_error_px": float(np.median(all_errors)),
        "mean_error_px": float(errors.mean()),
        "median_error_px": float(np.median(errors)),
        "rms_error_px": float(np.sqrt(np.mean(errors**2))),
        "p95_error_px": float(np.percentile(errors, 95)),
    }


def scene_from_rotation_only(
    images_dir: str | Path,
    out_dir: str | Path,
    options: RotationOnlyOptions | None = None,
    progress: ProgressCallback = no_progress,
    names: list[str] | None = None,
) -> dict[str, Any]:
    """Estimate a rotation-only station from the images in ``images_dir`` and write a scene folder.

    ``out_dir/images`` holds the registered frames, ``out_dir/sparse/0`` one PINHOLE camera
    and their rotations (every camera centre at the origin, no 3D points: one station cannot
    triangulate), ``out_dir/rotation_report.json`` the report returned. ``names`` restricts
    the frames used (file names inside ``images_dir``). Built atomically.
    """
    import shutil

    from ..colmap.io import write_model
    from ..formats.imageio import read_image
    from ..io_utils import atomic_directory, atomic_write_json

    options = options or RotationOnlyOptions()
    options.validate()
    files = list_images(images_dir)
    if names is not None:
        wanted = set(names)
        missing = wanted - {f.name for f in files}
        if missing:
            raise DatasetError(f"images not found: {sorted(missing)[:5]}", path=images_dir)
        files = [f for f in files if f.name in wanted]
    check_readable(files)
    estimate = estimate_rotations([read_image(f) for f in files], options, progress)
    registered = estimate["registered"]
    width, height = estimate["image_size"]
    focal = estimate["focal_px"]
    camera = Camera(1, "PINHOLE", width, height, np.array([focal, focal, *estimate["principal_point"]]))
    report = {
        key: value for key, value in estimate.items() if key not in ("rotations", "registered", "unregistered")
    }
    report.update(
        registered=[files[k].name for k in registered],
        unregistered=[files[k].name for k in estimate["unregistered"]],
        horizontal_fov_deg=2.0 * math.degrees(math.atan(width / 2.0 / focal)),
        limits="one camera station: no parallax, no triangulated points; geometry must come from priors",
    )
    with atomic_directory(out_dir, overwrite=options.overwrite) as staging:
        staged = SceneDir(staging)
        staged.images.mkdir()
        for k in registered:
            shutil.copyfile(files[k], staged.image(files[k].name))
        model = station_model(
            camera, [files[k].name for k in registered], [estimate["rotations"][k] for k in registered], source=str(SceneDir(out_dir).model)
        )
        write_model(model, staged.model, binary=True)
        atomic_write_json(staging / "rotation_report.json", report)
        atomic_write_json(staged.provenance, scene_provenance(
            "rotation-only", report["registered"], units="none: one station, no scale", points3d=0, report="rotation_report.json"))
    return report
