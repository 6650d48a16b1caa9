"""Depth of the surface a pixel sees: the Gaussian at which its transmittance crosses one half.

The rasterizer's expected depth, sum(w z) / sum(w), mixes every Gaussian a ray passes through.
Along a grazing ray (a rover view of the ground) that includes the upper parts of many
Gaussians before the surface, so a loss asking the expected depth to equal a prior's depth
pushes all of them down. The *median* surface of a pixel is instead the single Gaussian that
takes its transmittance from above one half to one half or below (``meta["median_ids"]`` of
the ``cpu`` and ``reference`` backends); only that Gaussian is asked to lie at the prior's depth.

Its depth at the pixel is read here, in torch, so gradients reach its mean and rotation by
autograd and no backend needs a backward of its own:

- ``"plane"``: where the pixel's ray meets the Gaussian's plane (the plane through its centre
  normal to its shortest axis), kept within ``extent`` of its largest standard deviations of
  the centre's depth: the depth a flat Gaussian actually shows at that pixel.
- ``"centre"``: the camera-z of its centre, the same at every pixel it covers.

The same Gaussian carries the normal prior (ESGS's ``normal_render``): its shortest axis
(:func:`median_surface_normals`) or its thickness along the prior normal
(:func:`median_surface_thinness`), which reach its rotation (and scales) but never its position.
"""
from __future__ import annotations

import torch

from ..errors import ConfigError
from .projection import quaternion_to_matrix

#: Plane depths are clamped to the centre's depth +- this many of the Gaussian's largest
#: standard deviations: a plane seen edge-on meets a ray far from the Gaussian itself.
PLANE_EXTENT_SIGMAS = 3.0

SURFACE_DEPTH_KINDS = ("plane", "centre")


def gaussian_normals(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """[N, 3] world-frame unit normals: each Gaussian's axis of smallest scale (sign arbitrary).

    quats: [N, 4] (w, x, y, z), any length; scales: [N, 3] activated. Which axis is shortest
    is a choice, not a function: no gradient flows through it.
    """
    rotation = quaternion_to_matrix(quats)  # columns are the Gaussian's axes
    shortest = torch.argmin(scales.detach(), dim=-1)
    index = shortest[:, None, None].expand(-1, 3, 1)
    return torch.gather(rotation, 2, index)[..., 0]


def camera_facing_normals(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                          viewmat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each Gaussian's shortest axis in one camera's frame, turned towards the camera
    (``n . centre <= 0``), and its centre in that frame: ([N, 3], [N, 3]).

    means [N, 3] world, quats [N, 4], scales [N, 3] (activated), viewmat [4, 4] world-to-camera.
    Which way the normal faces is a choice, not a function: no gradient flows through it.
    """
    rotation, translation = viewmat[:3, :3].to(means), viewmat[:3, 3].to(means)
    centres = means @ rotation.T + translation
    normals = gaussian_normals(quats, scales) @ rotation.T
    away = (normals * centres).sum(-1, keepdim=True).detach() > 0
    return torch.where(away, -normals, normals), centres


def pixel_rays(K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[H, W, 3] ``K^-1 (u, v, 1)`` at pixel centres (u = j + 0.5, v = i + 0.5): rays of unit z."""
    dtype, device = K.dtype, K.device
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=device) + 0.5,
                          torch.arange(width, dtype=dtype, device=device) + 0.5, indexing="ij")
    pixels = torch.stack([u, v, torch.ones_like(u)], dim=-1)
    return pixels @ torch.linalg.inv(K).T


def median_surface_depth(median_ids: torch.Tensor, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                         viewmat: torch.Tensor, K: torch.Tensor, *, kind: str = "plane",
                         extent: float = PLANE_EXTENT_SIGMAS) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth (camera z) of each pixel's median surface, differentiable w.r.t. the Gaussians.

    median_ids: [H, W] int64, the rasterizer's ``meta["median_ids"][camera]`` (-1: no
    surface); means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3] (activated): the
    Gaussians that were rendered; viewmat [4, 4] world-to-camera, K [3, 3]. Returns
    (depth [H, W], valid [H, W] bool); depth is 0 where ``valid`` is False.
    """
    if kind not in SURFACE_DEPTH_KINDS:
        raise ConfigError(f"surface depth kind must be one of {SURFACE_DEPTH_KINDS}, got {kind!r}")
    height, width = median_ids.shape
    valid = median_ids >= 0
    depth = torch.zeros((height, width), dtype=means.dtype, device=means.device)
    if not bool(valid.any()):
        return depth, valid
    ids = median_ids[valid].to(means.device)
    rotation = viewmat[:3, :3].to(means)
    centre = means[ids] @ rotation.T + viewmat[:3, 3].to(means)  # [M, 3] camera frame
    if kind == "centre":
        values = centre[:, 2]
    else:
        normal = gaussian_normals(quats[ids], scales[ids]) @ rotation.T
        ray = pixel_rays(K.to(means), width, height)[valid]  # z = 1: the ray's parameter is depth
        facing = (normal * ray).sum(-1)
        reach = extent * scales[ids].max(dim=-1).values
        edge_on = facing.abs() < 1e-6
        plane = (normal * centre).sum(-1) / torch.where(edge_on, torch.ones_like(facing), facing)
        plane = torch.where(edge_on, centre[:, 2], plane)
        values = torch.minimum(torch.maximum(plane, centre[:, 2] - reach), centre[:, 2] + reach)
    depth = depth.index_put((valid,), values)
    return depth, valid


def median_surface_normals(median_ids: torch.Tensor, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                           viewmat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-frame unit normal of each pixel's median surface Gaussian, facing the camera.

    The normal is the Gaussian's shortest axis (:func:`gaussian_normals`), turned towards the
    camera (``n . centre < 0``): the same normal the rasterizer composites, but of the one
    Gaussian at which the pixel's transmittance crosses one half. Gradients reach only that
    Gaussian's rotation: a loss on these normals turns Gaussians and never moves or fades them.
    Arguments as :func:`median_surface_depth`; returns (normals [H, W, 3], valid [H, W] bool),
    zero where ``valid`` is False.
    """
    height, width = median_ids.shape
    valid = median_ids >= 0
    normals = torch.zeros((height, width, 3), dtype=quats.dtype, device=quats.device)
    if not bool(valid.any()):
        return normals, valid
    ids = median_ids[valid].to(quats.device)
    normal, _ = camera_facing_normals(means[ids].detach(), quats[ids], scales[ids], viewmat)
    return normals.index_put((valid,), normal), valid


def _fused_on(*tensors: torch.Tensor) -> bool:
    """Whether the Numba kernel serves these tensors: all on the CPU, float32 or float64 values."""
    return all(t.device.type == "cpu" for t in tensors) and tensors[0].dtype in (torch.float32, torch.float64)


def median_surface_thinness(median_ids: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                            viewmat: torch.Tensor, normals: torch.Tensor,
                            fused: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """How thick each pixel's median surface Gaussian is along a given normal, in [0, 3].

    The Gaussian's variance along the unit normal over its mean variance,
    ``n^T Sigma n / (tr Sigma / 3)``: 0 for a disc lying across ``n``, 1 for a ball, up to 3
    for a needle along ``n``. Unlike the angle between ``n`` and the shortest axis it has a
    gradient in the scales too, so a loss on it both turns and flattens that one Gaussian,
    and never moves or fades it. median_ids [H, W], quats [N, 4], scales [N, 3] (activated),
    viewmat [4, 4]; normals [H, W, 3] camera frame (a prior's), sign free. Returns
    (thinness [H, W], valid [H, W] bool), 0 where ``valid`` is False. ``fused``: on CPU
    tensors, one Numba pass per pixel (:mod:`.surface_kernels`, the same values and gradients);
    False for the torch expression (the reference the tests compare it with).
    """
    valid = median_ids >= 0
    if fused and _fused_on(quats, scales, normals, median_ids):
        from .surface_kernels import fused_thinness  # Numba, loaded on first use

        return fused_thinness(median_ids, quats, scales, viewmat, normals), valid
    values = torch.zeros(median_ids.shape, dtype=quats.dtype, device=quats.device)
    if not bool(valid.any()):
        return values, valid
    ids = median_ids[valid].to(quats.device)
    world = normals[valid].to(quats) @ viewmat[:3, :3].to(quats)  # camera -> world: R^T n, as rows
    world = world / world.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    axes = quaternion_to_matrix(quats[ids])  # [M, 3, 3], columns = axes
    along = (axes * world[:, :, None]).sum(1)  # [M, 3]: a_k . n
    variance = scales[ids] ** 2
    thick = (variance * along ** 2).sum(-1) / (variance.sum(-1) / 3.0).clamp_min(1e-30)
    return values.index_put((valid,), thick), valid
