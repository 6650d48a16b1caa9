"""PGSR (Chen et al., "PGSR: Planar-based Gaussian Splatting for Efficient and High-Fidelity
Surface Reconstruction", TVCG 2024) as trainer hooks: planar Gaussians and their geometry losses.

Every Gaussian is treated as a small plane. Its normal is the axis of its smallest scale,
oriented towards the camera, and its plane's distance from the camera centre is
``d = -n . x`` (camera frame, ``x`` the centre; ``d >= 0`` for a normal facing the camera).
Both are composited per pixel through the rasterizer's ``extra`` channels (4 features:
normal, distance), so the rendered plane of a pixel is ``N . X = -D`` and the *unbiased
depth* along the pixel's ray ``r = K^-1 (u, v, 1)`` is ``z = D / (-N . r)``: the depth of the
ray-plane intersection, not the blurred mean of the Gaussians' centre depths.

The losses, each a registered loss term of the run:

- ``pgsr_flatten``: the mean smallest scale (as a fraction of the scene extent): flattens
  the Gaussians into discs so that "the axis of the smallest scale" is a normal;
- ``pgsr_single_view``: the normal of the unbiased depth map (finite differences of the
  back-projected points) against the rendered normal, L1, weighted by ``(1 - g)^2`` with
  ``g`` the min-max normalised image gradient, so image edges (likely depth edges) count less;
- ``pgsr_multi_view_geo``: for sampled pixels of the view, the homography of the rendered
  plane maps the pixel into a neighbouring training view; the neighbour's rendered plane
  there maps it back; the forward-backward pixel error ``phi`` is the loss, weighted by
  ``exp(-phi)`` (detached) and dropped at ``phi >= 1 px``;
- ``pgsr_multi_view_ncc``: grey 7x7 patches of the view's image against the neighbour's
  image warped through the same plane's homography, ``1 - NCC`` (clamped to [0, 2], patches
  at 0.9 or more dropped as occluded or mismatched), with the same weights.

The multi-view terms render the neighbour (with gradients) only on the steps where they are
active; both use one render and one pixel sample per step. PGSR's exposure compensation is
left out (our scenes have fixed exposure), as are its densification changes (the absolute
gradient criterion) and its mesh extraction (docs/baselines.md, "PGSR").
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Optional, Sequence

import torch
import torch.nn.functional as F

from ...render.surface import camera_facing_normals, pixel_rays
from ...train.gaussians import RenderParams
from ...train.hooks import RunView, StepContext, TrainHook
from ...train.losses import LossContext, LossTerm, flattening_loss
from .config import PGSRConfig

#: Mixed into the run seed so PGSR's sampling stream differs from every other.
_SEED_SALT = 0x9A5A
#: ITU-R BT.601 luma weights (the grey image of the NCC term and the edge weights).
_GREY = (0.299, 0.587, 0.114)
#: A pixel's plane is used only where the rendered normal is at least this long (something drawn).
_MIN_NORMAL_LENGTH = 1e-4
#: Rays grazing the rendered plane (|cos| below this) get no unbiased depth.
_MIN_COSINE = 1e-3


# --- per-Gaussian planes ----------------------------------------------------------------------
def plane_features(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                   viewmat: torch.Tensor) -> torch.Tensor:
    """[N, 4] per-Gaussian plane in one camera's frame: the normal (3, towards the camera) and
    the distance ``d = -n . x_cam >= 0`` of the plane from the camera centre (1).

    means: [N, 3] world; viewmat: [4, 4] world-to-camera (OpenCV axes).
    """
    normals, points = camera_facing_normals(means, quats, scales, viewmat)
    distance = -(normals * points).sum(-1, keepdim=True)
    return torch.cat([normals, distance], dim=-1)


# --- per-pixel geometry -----------------------------------------------------------------------
def unbiased_depth(normal_map: torch.Tensor, distance_map: torch.Tensor,
                   K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """PGSR's unbiased depth ``z = D / (-N . r)`` of the rendered planes.

    normal_map: [H, W, 3] composited normals (camera frame, not renormalised); distance_map:
    [H, W] composited distances; K: [3, 3]. Both maps carry the same compositing weights, so
    their ratio is the distance of the weighted plane. Returns ``(depth [H, W] camera z,
    valid [H, W] bool)``; depth is 0 where nothing is drawn or the ray grazes the plane.
    """
    height, width = distance_map.shape
    rays = pixel_rays(K.to(normal_map), width, height)
    length = normal_map.norm(dim=-1)
    cosine = -(normal_map * rays).sum(-1)
    valid = (length > _MIN_NORMAL_LENGTH) & (cosine > _MIN_COSINE * length * rays.norm(dim=-1))
    safe = torch.where(valid, cosine, torch.ones_like(cosine))
    depth = torch.where(valid, distance_map / safe, torch.zeros_like(distance_map))
    valid = valid & (depth > 0)
    return torch.where(valid, depth, torch.zeros_like(depth)), valid


def depth_to_normals(depth: torch.Tensor, K: torch.Tensor,
                     valid: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Normals of a depth map from central differences of its back-projected points.

    depth: [H, W] camera z; K: [3, 3]; valid: [H, W] bool or None (depth > 0). The normal
    at (i, j) is ``normalise((P[i+1, j] - P[i-1, j]) x (P[i, j+1] - P[i, j-1]))``, facing
    the camera (-z for a fronto-parallel plane). Returns ``(normals [H, W, 3], valid [H, W])``:
    the border and pixels with an invalid neighbour are invalid (normal 0).
    """
    height, width = depth.shape
    points = depth[..., None] * pixel_rays(K.to(depth), width, height)
    valid = (depth > 0) if valid is None else valid & (depth > 0)
    normals = torch.zeros_like(points)
    ok = torch.zeros_like(valid)
    if height >= 3 and width >= 3:
        dx = points[1:-1, 2:] - points[1:-1, :-2]
        dy = points[2:, 1:-1] - points[:-2, 1:-1]
        cross = torch.linalg.cross(dy, dx, dim=-1)
        length = cross.norm(dim=-1, keepdim=True)
        inner = (valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
                 & (length[..., 0] > 1e-12))
        unit = cross / torch.where(inner[..., None], length, torch.ones_like(length))
        normals = F.pad(torch.where(inner[..., None], unit, torch.zeros_like(unit)).permute(2, 0, 1),
                        (1, 1, 1, 1)).permute(1, 2, 0)
        ok = F.pad(inner, (1, 1, 1, 1))
    return normals, ok


def grey(image: torch.Tensor) -> torch.Tensor:
    """[H, W] luma of an [H, W, 3] image."""
    weights = torch.tensor(_GREY, dtype=image.dtype, device=image.device)
    return image @ weights


def edge_weights(image: torch.Tensor) -> torch.Tensor:
    """[H, W] PGSR's edge-aware weights ``(1 - g)^2`` of an [H, W, 3] image (no gradient).

    ``g``: per pixel the larger of the channel-averaged absolute central differences along x
    and y, min-max normalised over the image; the one-pixel border (no central difference)
    gets g = 1, weight 0.
    """
    image = image.detach()
    height, width = image.shape[:2]
    weights = torch.zeros(height, width, dtype=image.dtype, device=image.device)
    if height < 3 or width < 3:
        return weights
    gx = (image[1:-1, 2:] - image[1:-1, :-2]).abs().mean(-1)
    gy = (image[2:, 1:-1] - image[:-2, 1:-1]).abs().mean(-1)
    gradient = torch.maximum(gx, gy)
    low, span = gradient.min(), gradient.max() - gradient.min()
    normalised = (gradient - low) / span if float(span) > 0 else torch.zeros_like(gradient)
    weights[1:-1, 1:-1] = (1.0 - normalised.clamp(0.0, 1.0)) ** 2
    return weights


def single_view_loss(depth_normals: torch.Tensor, normals: torch.Tensor, weights: torch.Tensor,
                     valid: torch.Tensor) -> torch.Tensor:
    """Weighted L1 between depth-derived and rendered unit normals, summed over xyz, averaged
    over ``valid`` pixels. All maps [H, W, 3] / [H, W]."""
    count = valid.sum()
    if int(count) == 0:
        return normals.sum() * 0.0
    difference = (depth_normals - normals).abs().sum(-1)
    return (weights * difference * valid.to(difference)).sum() / count.to(difference)


# --- two views ----------------------------------------------------------------------------------
def relative_pose(viewmat_from: torch.Tensor, viewmat_to: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R [3, 3], t [3])`` with ``X_to = R X_from + t`` between two cameras' frames."""
    rotation = viewmat_to[:3, :3] @ viewmat_from[:3, :3].T
    return rotation, viewmat_to[:3, 3] - rotation @ viewmat_from[:3, 3]


def plane_homography(K_from: torch.Tensor, K_to: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor,
                     normals: torch.Tensor, distances: torch.Tensor) -> torch.Tensor:
    """[P, 3, 3] homographies ``K_to (R - t n^T / d) K_from^-1`` induced by planes ``n . X = -d``.

    normals: [P, 3] unit, camera ``from``'s frame; distances: [P] (> 0); rotation/translation:
    ``X_to = R X_from + t``. Maps homogeneous pixels (u, v, 1) of ``from`` to ``to``.
    """
    outer = translation[None, :, None] * normals[:, None, :] / distances[:, None, None]
    return K_to @ (rotation[None] - outer) @ torch.linalg.inv(K_from)


def apply_homography(H: torch.Tensor, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(pixels [P, M, 2], w [P, M])``: ``H [P, 3, 3]`` applied to ``pixels [P, M, 2]`` and the
    homogeneous scale (> 0 where the point lies in front of both cameras)."""
    homogeneous = torch.cat([pixels, torch.ones_like(pixels[..., :1])], dim=-1)
    mapped = homogeneous @ H.transpose(1, 2)
    w = mapped[..., 2]
    safe = torch.where(w.abs() > 1e-10, w, torch.full_like(w, 1e-10))
    return mapped[..., :2] / safe[..., None], w


def sample_map(image: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    """Bilinear samples ``[..., C]`` of ``image [H, W, C]`` at continuous pixel coordinates
    ``pixels [..., 2]`` (u, v; pixel (i, j) has its centre at (j + 0.5, i + 0.5)); 0 outside."""
    height, width = image.shape[:2]
    shape = pixels.shape[:-1]
    grid = torch.stack([2.0 * pixels[..., 0] / width - 1.0, 2.0 * pixels[..., 1] / height - 1.0], dim=-1)
    sampled = F.grid_sample(image.permute(2, 0, 1)[None], grid.reshape(1, -1, 1, 2).to(image), mode="bilinear",
                            padding_mode="zeros", align_corners=False)
    return sampled[0, :, :, 0].T.reshape(*shape, image.shape[2])


def inside(pixels: torch.Tensor, width: int, height: int, margin: float = 0.0) -> torch.Tensor:
    """[...] bool: ``pixels [..., 2]`` at least ``margin`` pixels inside the image."""
    return ((pixels[..., 0] >= margin) & (pixels[..., 0] <= width - margin)
            & (pixels[..., 1] >= margin) & (pixels[..., 1] <= height - margin))


def normalised_cross_correlation(first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
    """[P] NCC of patch pairs ``[P, M]`` (zero-mean, unit-variance correlation; 0 for a flat patch)."""
    a = first - first.mean(-1, keepdim=True)
    b = second - second.mean(-1, keepdim=True)
    return (a * b).sum(-1) / torch.sqrt((a * a).sum(-1) * (b * b).sum(-1) + 1e-8)


def patch_offsets(radius: int, dtype: torch.dtype = torch.float32, device: Any = "cpu") -> torch.Tensor:
    """[(2r + 1)^2, 2] integer (du, dv) offsets of a square patch, row by row."""
    steps = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    dv, du = torch.meshgrid(steps, steps, indexing="ij")
    return torch.stack([du.reshape(-1), dv.reshape(-1)], dim=-1)


def multi_view_losses(pixels: torch.Tensor, ref_normals: torch.Tensor, ref_distances: torch.Tensor,
                      neighbour_normal_map: torch.Tensor, neighbour_distance_map: torch.Tensor,
                      K_ref: torch.Tensor, K_neighbour: torch.Tensor, viewmat_ref: torch.Tensor,
                      viewmat_neighbour: torch.Tensor, *, ref_grey: Optional[torch.Tensor] = None,
                      neighbour_grey: Optional[torch.Tensor] = None, patch_radius: int = 3,
                      error_threshold: float = 1.0) -> dict[str, torch.Tensor]:
    """PGSR's multi-view geometric and photometric losses at sampled reference pixels.

    pixels: [P, 2] continuous pixel coordinates of the reference view (pixel centres);
    ref_normals: [P, 3] composited normals there (camera frame); ref_distances: [P]
    composited plane distances; neighbour_normal_map [H', W', 3] / neighbour_distance_map
    [H', W']: the neighbour's rendered planes; ref_grey [H, W] / neighbour_grey [H', W']:
    grey images for the NCC term (None: no NCC). Returns ``geo`` and ``ncc`` (0-dim),
    ``error`` [P] forward-backward pixel errors (0 where invalid), ``cost`` [P] ``1 - NCC``
    clamped to [0, 2], ``weight`` [P] (``exp(-error)`` below the threshold, else 0; no
    gradient), ``valid`` [P] (the pixel maps into the neighbour, in front of both cameras,
    onto a drawn plane) and ``kept`` [P] (patches of the NCC term). ``geo`` is
    ``sum(weight * error) / count(valid)``, ``ncc`` the mean of ``weight * cost`` over ``kept``.
    """
    dtype = ref_distances.dtype
    height_n, width_n = neighbour_distance_map.shape
    rotation, translation = relative_pose(viewmat_ref.to(dtype), viewmat_neighbour.to(dtype))
    K_ref, K_neighbour = K_ref.to(dtype), K_neighbour.to(dtype)

    length = ref_normals.norm(dim=-1)
    valid = length > _MIN_NORMAL_LENGTH
    safe_length = torch.where(valid, length, torch.ones_like(length))
    normals = ref_normals / safe_length[:, None]
    distances = ref_distances / safe_length
    valid = valid & (distances > 1e-8)
    distances = torch.where(valid, distances, torch.ones_like(distances))
    forward = plane_homography(K_ref, K_neighbour, rotation, translation, normals, distances)
    mapped, w = apply_homography(forward, pixels[:, None, :])
    mapped, w = mapped[:, 0], w[:, 0]
    valid = valid & (w > 1e-6) & inside(mapped, width_n, height_n)

    # the neighbour's rendered plane where the pixel lands, and its homography back
    back_normals_raw = sample_map(neighbour_normal_map, mapped)
    back_distances_raw = sample_map(neighbour_distance_map[..., None], mapped)[..., 0]
    back_length = back_normals_raw.norm(dim=-1)
    valid = valid & (back_length > _MIN_NORMAL_LENGTH)
    safe_back = torch.where(valid, back_length, torch.ones_like(back_length))
    back_distances = back_distances_raw / safe_back
    valid = valid & (back_distances > 1e-8)
    back_distances = torch.where(valid, back_distances, torch.ones_like(back_distances))
    rotation_back, translation_back = relative_pose(viewmat_neighbour.to(dtype), viewmat_ref.to(dtype))
    backward = plane_homography(K_neighbour, K_ref, rotation_back, translation_back,
                                back_normals_raw / safe_back[:, None], back_distances)
    returned, w_back = apply_homography(backward, mapped[:, None, :])
    valid = valid & (w_back[:, 0] > 1e-6)
    error = (pixels - returned[:, 0]).norm(dim=-1)
    error = torch.where(valid, error, torch.zeros_like(error))
    weight = torch.where(valid & (error.detach() < error_threshold), torch.exp(-error.detach()),
                         torch.zeros_like(error))
    count = valid.sum().clamp_min(1).to(dtype)
    geo = (weight * error).sum() / count

    ncc = error.sum() * 0.0
    cost = torch.zeros_like(error)
    kept = torch.zeros_like(valid)
    if ref_grey is not None and neighbour_grey is not None:
        offsets = patch_offsets(patch_radius, dtype, pixels.device)
        ref_patch_pixels = pixels[:, None, :] + offsets[None]
        ref_patches = sample_map(ref_grey[..., None].to(dtype), ref_patch_pixels)[..., 0]
        warped, w_patch = apply_homography(forward, ref_patch_pixels)
        neighbour_patches = sample_map(neighbour_grey[..., None].to(dtype), warped)[..., 0]
        patch_ok = valid & inside(mapped, width_n, height_n, margin=patch_radius) & (w_patch > 1e-6).all(-1)
        cost = (1.0 - normalised_cross_correlation(ref_patches, neighbour_patches)).clamp(0.0, 2.0)
        kept = patch_ok & (cost.detach() < 0.9)
        if bool(kept.any()):
            ncc = (cost * weight)[kept].mean()
    return {"geo": geo, "ncc": ncc, "error": error, "cost": cost, "weight": weight, "valid": valid, "kept": kept}


def neighbour_views(views: Sequence[Any], *, count: int = 8, max_angle_deg: float = 30.0) -> list[list[int]]:
    """For each view, the indices of up to ``count`` other views to pair it with, nearest
    camera centre first, among those whose viewing direction is within ``max_angle_deg``
    (the nearest one alone when none is). Views: objects with ``viewmat`` [4, 4]."""
    if len(views) < 2:
        return [[] for _ in views]
    viewmats = torch.stack([view.viewmat.detach().to(torch.float64).cpu() for view in views])
    rotations = viewmats[:, :3, :3]
    centres = -(rotations.transpose(1, 2) @ viewmats[:, :3, 3:])[..., 0]
    directions = rotations[:, 2, :]  # each camera's +z axis in the world
    distance = torch.cdist(centres, centres)
    cosine = (directions @ directions.T).clamp(-1.0, 1.0)
    limit = math.cos(math.radians(max_angle_deg))
    result = []
    for index in range(len(views)):
        order = [int(other) for other in torch.argsort(distance[index]) if int(other) != index]
        close = [other for other in order if float(cosine[index, other]) >= limit - 1e-12]
        result.append(close[:count] if close else order[:1])
    return result


# --- the hook -------------------------------------------------------------------------------
class PGSRHook(TrainHook):
    """Adds PGSR's loss terms; composites the plane channels on the steps that use them."""

    name = "baseline_pgsr"

    def __init__(self, config: PGSRConfig):
        self.config = config
        self.extent = 1.0
        self.neighbours: list[list[int]] = []
        self.terms: list[LossTerm] = []
        self._views: dict[str, int] = {}
        self._edge: dict[str, torch.Tensor] = {}
        self._grey: dict[str, torch.Tensor] = {}

    def setup(self, run: RunView) -> None:
        config = self.config
        views = list(run.train_views)
        self._views = {view.name: index for index, view in enumerate(views)}
        self.extent = run.extent
        self.neighbours = neighbour_views(views, count=config.pgsr_neighbours,
                                          max_angle_deg=config.pgsr_neighbour_max_angle_deg)
        single_from = run.scaled_step(config.pgsr_single_view_from)
        multi_from = run.scaled_step(config.pgsr_multi_view_from)
        self.terms = [LossTerm("pgsr_flatten", config.pgsr_flatten_weight, self._flatten_term)]
        self.terms.append(LossTerm("pgsr_single_view", config.pgsr_single_view_weight, self._single_view_term,
                                   start_step=single_from))
        if len(views) >= 2:
            self.terms.append(LossTerm("pgsr_multi_view_geo", config.pgsr_multi_view_geo_weight, self._geo_term,
                                       start_step=multi_from))
            self.terms.append(LossTerm("pgsr_multi_view_ncc", config.pgsr_multi_view_ncc_weight, self._ncc_term,
                                       start_step=multi_from))
        else:
            run.message("note: PGSR's multi-view losses need two training views or more; they are off")
        for term in self.terms:
            run.add_loss_term(term)

    def planes_needed(self, step: int) -> bool:
        """Whether a term that reads the plane channels is active at ``step``."""
        return any(term.active(step) for term in self.terms if term.name != "pgsr_flatten")

    def before_render(self, run: RunView, context: StepContext, params: RenderParams) -> Optional[RenderParams]:
        if not self.planes_needed(context.step):
            return params
        features = plane_features(params.means, params.quats, params.scales, context.view.viewmat.to(params.means))
        return replace(params, extra=features)

    # --- loss terms ------------------------------------------------------------------------
    def _flatten_term(self, context: LossContext) -> torch.Tensor:
        return flattening_loss(context.params.scales, self.extent)

    def _planes(self, context: LossContext) -> tuple[torch.Tensor, torch.Tensor]:
        extra = context.output.extra if context.output is not None else None
        if extra is None or extra.shape[-1] < 4:
            raise RuntimeError("PGSR's plane channels were not rendered (another hook replaced the extra channels)")
        return extra[..., :3], extra[..., 3]

    def _single_view_term(self, context: LossContext) -> torch.Tensor:
        normal_map, distance_map = self._planes(context)
        K = context.view.K.to(distance_map)
        depth, valid = unbiased_depth(normal_map, distance_map, K)
        valid = valid & (context.alpha[..., 0].detach() > 0.5)
        if context.mask is not None:
            valid = valid & context.mask[..., 0]
        depth_normals, ok = depth_to_normals(depth, K, valid)
        length = normal_map.norm(dim=-1, keepdim=True)
        rendered = normal_map / length.clamp_min(_MIN_NORMAL_LENGTH)
        return single_view_loss(depth_normals, rendered, self._edge_weights(context), ok & valid)

    def _edge_weights(self, context: LossContext) -> torch.Tensor:
        name = context.view.name
        if name not in self._edge:
            self._edge[name] = edge_weights(context.target)
        return self._edge[name]

    def _grey_of(self, view: Any, device: Any) -> torch.Tensor:
        if view.name not in self._grey:
            self._grey[view.name] = grey(view.image_float(device))
        return self._grey[view.name]

    def _geo_term(self, context: LossContext) -> torch.Tensor:
        return self._multi_view(context)["geo"]

    def _ncc_term(self, context: LossContext) -> torch.Tensor:
        return self._multi_view(context)["ncc"]

    def _multi_view(self, context: LossContext) -> dict[str, torch.Tensor]:
        """Both multi-view losses of this step, computed once (one neighbour render, one sample)."""
        if "pgsr_multi_view" in context.cache:
            return context.cache["pgsr_multi_view"]
        zero = context.image.sum() * 0.0
        result = {"geo": zero, "ncc": zero}
        index = self._views.get(context.view.name)
        run = context.run
        if index is None or run is None or not self.neighbours[index]:
            context.cache["pgsr_multi_view"] = result
            return result
        generator = torch.Generator(device="cpu")
        generator.manual_seed((int(run.seed) * 1_000_003 + int(context.step) * 7919 + _SEED_SALT) % (2 ** 63))
        choices = self.neighbours[index]
        neighbour = run.train_views[choices[int(torch.randint(len(choices), (1,), generator=generator))]]

        normal_map, distance_map = self._planes(context)
        height, width = distance_map.shape
        radius = self.config.pgsr_patch_radius
        candidates = (normal_map.detach().norm(dim=-1) > _MIN_NORMAL_LENGTH) & (context.alpha[..., 0].detach() > 0.5)
        if context.mask is not None:
            candidates = candidates & context.mask[..., 0]
        border = torch.zeros_like(candidates)
        border[radius:height - radius, radius:width - radius] = True
        flat = torch.nonzero((candidates & border).reshape(-1)).reshape(-1).cpu()
        if flat.numel() == 0:
            context.cache["pgsr_multi_view"] = result
            return result
        if flat.numel() > self.config.pgsr_multi_view_samples:
            flat = flat[torch.randperm(flat.numel(), generator=generator)[:self.config.pgsr_multi_view_samples]]
        flat = flat.to(distance_map.device)
        rows, cols = flat // width, flat % width
        pixels = torch.stack([cols, rows], dim=-1).to(distance_map) + 0.5

        params = context.params
        device_viewmat = neighbour.viewmat.to(params.means)
        neighbour_params = replace(params, extra=plane_features(params.means, params.quats, params.scales,
                                                                device_viewmat))
        output = run.render(neighbour_params, neighbour)
        neighbour_extra = output.extra
        result = multi_view_losses(
            pixels, normal_map[rows, cols], distance_map[rows, cols], neighbour_extra[..., :3], neighbour_extra[..., 3],
            context.view.K.to(distance_map), neighbour.K.to(distance_map), context.view.viewmat.to(distance_map),
            neighbour.viewmat.to(distance_map), ref_grey=grey(context.target),
            neighbour_grey=self._grey_of(neighbour, distance_map.device), patch_radius=radius,
            error_threshold=self.config.pgsr_pixel_error_threshold)
        context.cache["pgsr_multi_view"] = result
        return result
