"""Multi-view plane-sweep stereo on the CPU: one depth map per view from calibrated images.

Why a plane sweep and not rectified two-view stereo (OpenCV's StereoSGBM): rover sequences
move forward, so the epipole lies in or near the image and rectification stretches the
views without bound; a plane sweep works for any relative pose, uses several neighbours
at once (occlusions are voted out) and needs nothing beyond ``cv2.warpPerspective``.

For a reference view and each depth hypothesis ``d`` (a plane in the reference camera),
every neighbour image is warped into the reference view through the plane's homography
and compared with zero-mean normalised cross-correlation (ZNCC) over a square window.
Two plane families are swept: fronto-parallel planes and planes parallel to the ground
(fitted to the sparse points), because ground seen at a grazing angle is far from
fronto-parallel and a window on it only matches on a ground-parallel plane (multiple
sweeping directions in the manner of Gallup et al., CVPR 2007). Per pixel the cost is
the mean of the best ``best_of`` neighbour costs (occlusion robustness), the best
hypothesis wins, its depth is refined by a parabola through the neighbouring costs, and
pixels whose best correlation is low or whose window has no texture are dropped, as are
pixels whose winner barely beats the hypotheses more than a few planes away: a flat cost
curve (a smooth sky, a brightness gradient) matches at many depths, and on rover views the
depths it picks lie at the far end of the range and build a lip along the horizon that
hides the far ground in every rendered label.

Depth hypotheses are uniform in inverse depth between bounds taken from the sparse
points the view observes (COLMAP ``points3D``), widened by a margin.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import ConfigError, DatasetError


@dataclass
class StereoOptions:
    """Settings of the plane sweep (see the module docstring)."""

    neighbours: int = field(default=4, metadata={"help": "neighbouring views compared with each view"})
    best_of: int = field(default=2, metadata={"help": "average the best this many neighbour costs per pixel"})
    planes: int = field(default=96, metadata={"help": "depth hypotheses per plane family"})
    window_px: int = field(default=7, metadata={"help": "ZNCC window side in pixels (odd)"})
    min_correlation: float = field(default=0.6, metadata={"help": "drop pixels whose best ZNCC is lower"})
    min_texture: float = field(default=2.0, metadata={"help": "drop pixels whose window's grey-level std (0-255) is lower"})
    min_distinctness: float = field(default=0.03, metadata={
        "help": "drop pixels whose best cost (1 - ZNCC) beats every hypothesis more than DISTINCT_PLANES planes "
                "away by less than this: a flat cost curve (smooth sky, a gradient) has no depth (0 = off)"})
    depth_margin: float = field(default=1.3, metadata={"help": "widen the sparse points' depth range by this factor"})
    ground_planes: bool = field(default=True, metadata={"help": "also sweep planes parallel to the fitted ground"})

    def validate(self) -> None:
        if self.neighbours < 1:
            raise ConfigError(f"neighbours must be >= 1, got {self.neighbours}")
        if not 1 <= self.best_of <= self.neighbours:
            raise ConfigError(f"best_of must be in [1, neighbours], got {self.best_of}")
        if self.planes < 8:
            raise ConfigError(f"planes must be >= 8, got {self.planes}")
        if self.window_px < 3 or self.window_px % 2 == 0:
            raise ConfigError(f"window_px must be odd and >= 3, got {self.window_px}")
        if not -1.0 < self.min_correlation < 1.0:
            raise ConfigError(f"min_correlation must be in (-1, 1), got {self.min_correlation}")
        if self.min_distinctness < 0:
            raise ConfigError(f"min_distinctness must be >= 0, got {self.min_distinctness}")
        if self.depth_margin < 1.0:
            raise ConfigError(f"depth_margin must be >= 1, got {self.depth_margin}")


@dataclass
class View:
    """One calibrated image. image: [H, W] float32 grey 0-255; K: [3, 3] (pixel centres at
    +0.5, COLMAP's convention); world_to_camera: [4, 4]; depth_range: (near, far) in scene
    units; point_ids: ids of the sparse points it observes; ground_offsets: (low, high) > 0
    of ``n . X`` for the ground points X it sees (camera frame, ``n`` the ground normal
    oriented to make them positive), None without a ground sweep."""

    name: str
    image: np.ndarray
    K: np.ndarray
    world_to_camera: np.ndarray
    depth_range: tuple[float, float]
    point_ids: frozenset[int] = frozenset()
    ground_offsets: tuple[float, float] | None = None  # range of n.X (camera frame) over the ground, n = ground normal

    @property
    def center(self) -> np.ndarray:
        rotation = self.world_to_camera[:3, :3]
        return -rotation.T @ self.world_to_camera[:3, 3]


def choose_neighbours(views: list[View], count: int) -> list[list[int]]:
    """For each view, the ``count`` other views best suited for stereo with it.

    Score: sparse points seen by both, times a factor that rises with the triangulation
    angle up to 5 degrees (tiny baselines measure depth badly) and falls to 0 when the
    optical axes differ by more than 60 degrees. Without shared points, the nearest
    camera centres with compatible viewing directions are taken.
    """
    neighbours = []
    for index, view in enumerate(views):
        forward = view.world_to_camera[2, :3]
        distance_scale = float(np.mean(view.depth_range))
        scores = []
        for other_index, other in enumerate(views):
            if other_index == index:
                continue
            axis_angle = np.degrees(np.arccos(np.clip(forward @ other.world_to_camera[2, :3], -1, 1)))
            if axis_angle > 60:
                continue
            baseline = float(np.linalg.norm(other.center - view.center))
            angle = np.degrees(2 * np.arctan2(baseline / 2, distance_scale))
            shared = len(view.point_ids & other.point_ids) if view.point_ids else 0
            weight = min(1.0, angle / 5.0)
            score = shared * weight if view.point_ids else weight / (1.0 + baseline / distance_scale)
            if score > 0:
                scores.append((score, other_index))
        scores.sort(reverse=True)
        neighbours.append([other for _, other in scores[:count]])
    return neighbours


def _opencv_K(K: np.ndarray) -> np.ndarray:
    """COLMAP K (pixel centres at +0.5) -> OpenCV warp K (pixel centres at integers)."""
    shifted = np.array(K, dtype=np.float64)
    shifted[0, 2] -= 0.5
    shifted[1, 2] -= 0.5
    return shifted


def _box(image: np.ndarray, window: int) -> np.ndarray:
    import cv2

    return cv2.boxFilter(image, cv2.CV_32F, (window, window), normalize=True, borderType=cv2.BORDER_REFLECT)


#: Hypotheses this close to the winner (in plane index) are its own minimum, not a rival.
DISTINCT_PLANES = 3


def _distinctness(costs: np.ndarray, winner: np.ndarray, cost_min: np.ndarray) -> np.ndarray:
    """[H, W]: the lowest cost of ``costs`` [P, H, W] more than :data:`DISTINCT_PLANES` planes
    from ``winner`` [H, W], minus the winning cost ``cost_min`` (inf when there is none): how
    clearly the winner stands out of its cost curve. One plane at a time: a full-size stack
    would be copied whole otherwise."""
    rival = np.full(winner.shape, np.inf, np.float32)
    for index in range(len(costs)):
        far = np.abs(index - winner) > DISTINCT_PLANES
        rival = np.where(far, np.minimum(rival, costs[index]), rival)
    return (rival - cost_min).astype(np.float32)


def plane_sweep_depth(reference: View, others: list[View], options: StereoOptions,
                      ground_normal_world: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Depth map of ``reference`` from its neighbours ``others``.

    Returns (depth [H, W] float32 along the camera z axis, 0 = rejected; correlation [H, W]
    float32, the best mean ZNCC). ``ground_normal_world`` [3] (oriented as for
    ``reference.ground_offsets``) adds the ground-parallel sweep.
    """
    import cv2

    options.validate()
    if not others:
        raise DatasetError(f"view {reference.name!r} has no neighbour for stereo",
                           hint="labels from --reconstruct need overlapping views taken from different positions")
    height, width = reference.image.shape
    window = options.window_px
    ref = reference.image.astype(np.float32)
    ref_mean = _box(ref, window)
    ref_var = np.maximum(_box(ref * ref, window) - ref_mean ** 2, 0.0)
    ref_std = np.sqrt(ref_var)
    K_ref_inv = np.linalg.inv(_opencv_K(reference.K))
    near, far = reference.depth_range
    # plane families: (unit normal n in the reference camera, plane offsets d with n.X = d)
    families = [(np.array([0.0, 0.0, 1.0]), 1.0 / np.linspace(1.0 / near, 1.0 / far, options.planes))]
    if options.ground_planes and ground_normal_world is not None and reference.ground_offsets is not None:
        normal = reference.world_to_camera[:3, :3] @ np.asarray(ground_normal_world, np.float64)
        low, high = reference.ground_offsets
        families.append((normal, 1.0 / np.linspace(1.0 / low, 1.0 / high, options.planes)))
    v_grid, u_grid = np.mgrid[0:height, 0:width].astype(np.float64)
    pixel_rays = np.stack([u_grid, v_grid, np.ones_like(u_grid)], axis=-1) @ K_ref_inv.T  # [H, W, 3], z = 1

    best_cost = np.full((height, width), np.inf, np.float32)
    best_depth = np.zeros((height, width), np.float32)
    best_distinctness = np.zeros((height, width), np.float32)
    for normal, offsets in families:
        costs = np.empty((len(offsets), height, width), np.float32)
        for plane_index, offset in enumerate(offsets):
            per_neighbour = []
            for other in others:
                relative = other.world_to_camera @ np.linalg.inv(reference.world_to_camera)
                rotation, translation = relative[:3, :3], relative[:3, 3]
                homography = _opencv_K(other.K) @ (rotation + np.outer(translation, normal) / offset) @ K_ref_inv
                warped = cv2.warpPerspective(other.image.astype(np.float32), homography, (width, height),
                                             flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                             borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
                inside = np.isfinite(warped)
                warped = np.where(inside, warped, 0.0).astype(np.float32)
                mean = _box(warped, window)
                var = np.maximum(_box(warped * warped, window) - mean ** 2, 0.0)
                cov = _box(ref * warped, window) - ref_mean * mean
                zncc = cov / np.sqrt(np.maximum(ref_var * var, 1e-6))
                coverage = _box(inside.astype(np.float32), window)
                cost = np.where(coverage > 0.99, 1.0 - zncc, 2.0)
                per_neighbour.append(cost)
            stack = np.sort(np.stack(per_neighbour), axis=0)
            costs[plane_index] = stack[:options.best_of].mean(axis=0)
        winner = np.argmin(costs, axis=0)
        cost_min = np.take_along_axis(costs, winner[None], axis=0)[0]
        # parabola through the neighbouring hypotheses' costs -> sub-plane offset (in inverse offset)
        inverse = 1.0 / offsets
        lower = np.clip(winner - 1, 0, len(offsets) - 1)
        upper = np.clip(winner + 1, 0, len(offsets) - 1)
        cost_lower = np.take_along_axis(costs, lower[None], axis=0)[0]
        cost_upper = np.take_along_axis(costs, upper[None], axis=0)[0]
        curvature = cost_lower + cost_upper - 2 * cost_min
        shift = np.where((curvature > 1e-6) & (lower != winner) & (upper != winner),
                         0.5 * (cost_lower - cost_upper) / np.maximum(curvature, 1e-6), 0.0)
        step = inverse[1] - inverse[0]
        refined_inverse = inverse[winner] + np.clip(shift, -0.5, 0.5) * step
        # depth along z of the ray (z = 1) meeting the plane n.X = offset
        depth = 1.0 / (refined_inverse * (pixel_rays @ normal))
        interior = (winner > 0) & (winner < len(offsets) - 1)  # a minimum at the range's end is no minimum
        better = interior & (cost_min < best_cost) & (depth > 0)
        best_cost = np.where(better, cost_min, best_cost)
        best_depth = np.where(better, depth, best_depth).astype(np.float32)
        if options.min_distinctness > 0:
            best_distinctness = np.where(better, _distinctness(costs, winner, cost_min), best_distinctness)
    correlation = (1.0 - best_cost).astype(np.float32)
    keep = (correlation >= options.min_correlation) & (ref_std >= options.min_texture) & (best_depth > 0)
    if options.min_distinctness > 0:
        keep &= best_distinctness >= options.min_distinctness
    return np.where(keep, best_depth, 0.0).astype(np.float32), np.where(keep, correlation, 0.0).astype(np.float32)


def consistent_depths(views: list[View], depths: list[np.ndarray], neighbours: list[list[int]],
                      relative_tolerance: float = 0.01, min_agreeing: int = 1) -> list[np.ndarray]:
    """Keep the pixels whose depth other views confirm.

    A pixel of view i is lifted to 3D with its depth, projected into each neighbour j, and
    agrees when j's depth map at that pixel (nearest) is within ``relative_tolerance`` of
    the point's depth in j. Pixels with fewer than ``min_agreeing`` agreeing neighbours are
    set to 0. depths: per view [H, W] (0 = none). Returns the filtered maps.
    """
    filtered = []
    for index, (view, depth) in enumerate(zip(views, depths)):
        height, width = depth.shape
        rows, cols = np.nonzero(depth > 0)
        z = depth[rows, cols].astype(np.float64)
        K_inv = np.linalg.inv(view.K)
        points_camera = (np.stack([cols + 0.5, rows + 0.5, np.ones_like(z)], axis=1) @ K_inv.T) * z[:, None]
        camera_to_world = np.linalg.inv(view.world_to_camera)
        points_world = points_camera @ camera_to_world[:3, :3].T + camera_to_world[:3, 3]
        agree = np.zeros(len(z), np.int32)
        for other_index in neighbours[index]:
            other, other_depth = views[other_index], depths[other_index]
            in_other = points_world @ other.world_to_camera[:3, :3].T + other.world_to_camera[:3, 3]
            z_other = in_other[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                uv = (in_other @ other.K.T)[:, :2] / z_other[:, None]
            u = np.floor(uv[:, 0]).astype(np.int64)
            v = np.floor(uv[:, 1]).astype(np.int64)
            other_height, other_width = other_depth.shape
            inside = (z_other > 0) & (u >= 0) & (v >= 0) & (u < other_width) & (v < other_height)
            sampled = np.zeros(len(z))
            sampled[inside] = other_depth[v[inside], u[inside]]
            agree += (inside & (sampled > 0) & (np.abs(sampled - z_other) <= relative_tolerance * z_other)).astype(np.int32)
        result = np.zeros_like(depth)
        keep = agree >= min_agreeing
        result[rows[keep], cols[keep]] = depth[rows[keep], cols[keep]]
        filtered.append(result)
    return filtered


def depth_maps(views: list[View], options: StereoOptions | None = None, *,
               ground_normal_world: np.ndarray | None = None,
               progress: Callable[[int, int, str], None] | None = None) -> tuple[list[np.ndarray], list[list[int]]]:
    """Plane-sweep depth maps [H, W] of every view (0 = none) and the neighbours used."""
    options = options or StereoOptions()
    options.validate()
    neighbours = choose_neighbours(views, options.neighbours)
    depths = []
    for index, view in enumerate(views):
        others = [views[j] for j in neighbours[index]]
        sweep_options = options
        if len(others) < options.best_of:
            from dataclasses import replace

            sweep_options = replace(options, best_of=max(1, len(others)))
        depth, _ = plane_sweep_depth(view, others, sweep_options, ground_normal_world)
        depths.append(depth)
        if progress is not None:
            progress(index + 1, len(views), view.name)
    return depths, neighbours
