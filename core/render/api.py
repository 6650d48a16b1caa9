"""The one public entry point of the rasterizer: :func:`rasterization`."""
from __future__ import annotations

from typing import Callable

import torch

from ..errors import ConfigError
from .constants import FAR_PLANE, NEAR_PLANE
from .sh import SHCoefficients, evaluate_sh_colors, num_sh_bases

BACKENDS = ("cpu", "reference", "cuda")
#: The backends whose ``meta`` names each pixel's median-surface Gaussian (``median_ids``;
#: gsplat, behind ``cuda``, has no such output).
MEDIAN_SURFACE_BACKENDS = frozenset({"cpu", "reference"})


def _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                  backgrounds, extra, backend, tile_size, near_plane, far_plane):
    if backend not in BACKENDS:
        raise ConfigError(f"unknown rasterizer backend {backend!r}", hint=f"use one of {', '.join(BACKENDS)}")
    tensors = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "viewmats": viewmats, "Ks": Ks}
    if isinstance(colors, SHCoefficients):
        if sh_degree is None:
            raise ConfigError("rasterization: colors given as SHCoefficients need sh_degree",
                              hint="pass sh_degree, or colors as an [N, D] tensor of features")
        tensors.update({"colors.dc": colors.dc, "colors.rest": colors.rest})
    else:
        tensors["colors"] = colors
    if backgrounds is not None:
        tensors["backgrounds"] = backgrounds
    if extra is not None:
        tensors["extra"] = extra
    for name, tensor in tensors.items():
        if not isinstance(tensor, torch.Tensor):
            raise ConfigError(f"rasterization: {name} must be a torch.Tensor, got {type(tensor).__name__}")
        if not tensor.is_floating_point():
            raise ConfigError(f"rasterization: {name} must be a floating-point tensor, got {tensor.dtype}")
    dtypes = {tensor.dtype for tensor in tensors.values()}
    if len(dtypes) != 1:
        raise ConfigError(f"rasterization: all tensors must share one dtype, got {sorted(map(str, dtypes))}",
                          hint="convert them with .float() or .double()")
    count = means.shape[0] if means.dim() == 2 else -1
    expected = {"means": (count, 3), "quats": (count, 4), "scales": (count, 3), "opacities": (count,)}
    for name, shape in expected.items():
        if count < 0 or tuple(tensors[name].shape) != shape:
            raise ConfigError(f"rasterization: {name} has shape {tuple(tensors[name].shape)}, expected {shape} "
                              "(N Gaussians)")
    if sh_degree is None:
        if colors.dim() != 2 or colors.shape[0] != count:
            raise ConfigError(f"rasterization: colors has shape {tuple(colors.shape)}, expected [N, D] "
                              "(or [N, K, 3] with sh_degree)")
    else:
        if not 0 <= int(sh_degree) <= 3:
            raise ConfigError(f"rasterization: sh_degree must be 0..3, got {sh_degree}")
        if isinstance(colors, SHCoefficients) and (
                colors.dc.dim() != 3 or tuple(colors.dc.shape[1:]) != (1, 3) or colors.rest.dim() != 3
                or colors.rest.shape[0] != colors.dc.shape[0] or colors.rest.shape[2] != 3):
            raise ConfigError(f"rasterization: SHCoefficients have dc {tuple(colors.dc.shape)} and rest "
                              f"{tuple(colors.rest.shape)}, expected [{count}, 1, 3] and [{count}, K-1, 3]")
        if len(colors.shape) != 3 or colors.shape[0] != count or colors.shape[2] != 3 \
                or colors.shape[1] < num_sh_bases(sh_degree):
            raise ConfigError(f"rasterization: SH colors have shape {tuple(colors.shape)}, expected [N, K>="
                              f"{num_sh_bases(sh_degree)}, 3] for sh_degree={sh_degree}")
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4):
        raise ConfigError(f"rasterization: viewmats has shape {tuple(viewmats.shape)}, expected [C, 4, 4]")
    cameras = viewmats.shape[0]
    if tuple(Ks.shape) != (cameras, 3, 3):
        raise ConfigError(f"rasterization: Ks has shape {tuple(Ks.shape)}, expected [{cameras}, 3, 3]")
    color_dims = colors.shape[-1]
    if backgrounds is not None and tuple(backgrounds.shape) != (cameras, color_dims):
        raise ConfigError(f"rasterization: backgrounds has shape {tuple(backgrounds.shape)}, "
                          f"expected [{cameras}, {color_dims}]")
    if extra is not None and (extra.dim() != 2 or extra.shape[0] != count):
        raise ConfigError(f"rasterization: extra has shape {tuple(extra.shape)}, expected [N, E]")
    if int(width) < 1 or int(height) < 1:
        raise ConfigError(f"rasterization: image size must be positive, got {width} x {height}")
    if int(tile_size) < 1:
        raise ConfigError(f"rasterization: tile_size must be positive, got {tile_size}")
    if not 0 < near_plane < far_plane:
        raise ConfigError(f"rasterization: need 0 < near_plane < far_plane, got {near_plane}, {far_plane}")


def _color_evaluator(means, colors, viewmats, sh_degree, fused: bool = False) -> Callable[[int], torch.Tensor]:
    """Per-camera colour features: raw ``colors`` or SH evaluated towards that camera.

    ``fused``: the SH in one Numba pass (:mod:`.sh_kernels`; the ``cpu`` backend), which keeps
    no per-basis temporaries for the backward; otherwise the torch expression (``reference``
    and ``cuda``), which the tests compare it with.
    """
    if sh_degree is None:
        return lambda cam: colors
    fused = fused and means.device.type == "cpu" and means.dtype in (torch.float32, torch.float64)
    if isinstance(colors, SHCoefficients) and not fused:
        colors = colors.cat()  # once for every camera: the torch expression takes one tensor

    def evaluate(cam: int) -> torch.Tensor:
        rotation = viewmats[cam, :3, :3]
        centre = -rotation.T @ viewmats[cam, :3, 3]
        if fused:
            from .sh_kernels import fused_sh_colors

            return fused_sh_colors(int(sh_degree), colors, means - centre)
        return evaluate_sh_colors(int(sh_degree), colors, means - centre)

    return evaluate


def rasterization(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor | SHCoefficients,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    *,
    near_plane: float = NEAR_PLANE,
    far_plane: float = FAR_PLANE,
    sh_degree: int | None = None,
    backgrounds: torch.Tensor | None = None,
    render_depth: bool = False,
    render_normals: bool = False,
    extra: torch.Tensor | None = None,
    antialiased: bool = False,
    eps2d: float = 0.3,
    tile_size: int = 16,
    num_threads: int | None = None,
    backend: str = "cpu",
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Render 3D Gaussians into C cameras (differentiable).

    means: [N, 3] world positions; quats: [N, 4] (w, x, y, z), normalised here;
    scales: [N, 3] activated (positive); opacities: [N] activated in [0, 1];
    colors: [N, D] features, or [N, K, 3] SH coefficients when ``sh_degree`` is given
    (colour = max(SH(view direction) + 0.5, 0), view direction = mean - camera centre), or
    those coefficients as :class:`~.sh.SHCoefficients` (``dc`` [N, 1, 3] and ``rest``
    [N, K-1, 3], a trainer's two parameters: the ``cpu`` backend then makes no [N, K, 3] copy);
    viewmats: [C, 4, 4] world-to-camera (OpenCV axes: x right, y down, z forward);
    Ks: [C, 3, 3] pixel intrinsics, pixel (i, j) has its centre at (j + 0.5, i + 0.5);
    backgrounds: [C, D] added as (1 - alpha) * background to the colour channels only;
    extra: [N, E] further per-Gaussian channels composited like colours.

    Returns ``render [C, H, W, X]`` (colour D, expected depth 1 if ``render_depth``, normals 3
    if ``render_normals``, extra E), ``alpha [C, H, W, 1]`` and ``meta`` with
    ``means2d [C, N, 2]`` (``retain_grad()`` is called when it needs grad),
    ``radii [C, N]`` int32 (0 = culled), ``depths [C, N]`` (camera z), ``channels``
    (slices), backend statistics and, from the ``cpu`` and ``reference`` backends,
    ``median_ids [C, H, W]`` int64: the Gaussian at which each pixel's transmittance first
    falls to one half or below, -1 where it stays above (its depth: :mod:`.surface`).

    Expected depth is sum(w z) / sum(w) (0 where nothing is hit); normals are each Gaussian's
    shortest axis in the camera frame, flipped towards the camera, composited as sum(w n).
    ``antialiased`` dilates the 2D covariance by ``eps2d`` and scales opacity by
    sqrt(det(cov) / det(cov + eps2d I)); otherwise a fixed 0.3 px^2 dilation is added, as in 3DGS.
    ``backend``: "cpu" (Numba kernels, hand-written backward), "reference" (dense torch, for
    tests) or "cuda" (gsplat, when installed). Bad input raises :class:`ConfigError`.
    """
    width, height = int(width), int(height)
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                  backgrounds, extra, backend, tile_size, near_plane, far_plane)
    color_dims = 3 if sh_degree is not None else colors.shape[-1]
    evaluate_colors = _color_evaluator(means, colors, viewmats, sh_degree, fused=backend == "cpu")
    options = dict(near_plane=float(near_plane), far_plane=float(far_plane), sh_degree=sh_degree,
                   backgrounds=backgrounds, render_depth=render_depth, render_normals=render_normals,
                   extra=extra, antialiased=antialiased, eps2d=float(eps2d))
    if backend == "reference":
        from .reference import rasterize_reference
        render, alpha, meta = rasterize_reference(means, quats, scales, opacities, colors, viewmats, Ks,
                                                  width, height, evaluate_colors=evaluate_colors, **options)
    elif backend == "cpu":
        from .cpu import rasterize_cpu
        render, alpha, meta = rasterize_cpu(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                            evaluate_colors=evaluate_colors, tile_size=int(tile_size),
                                            num_threads=num_threads, **options)
    else:
        from .cuda import rasterize_cuda
        render, alpha, meta = rasterize_cuda(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                             evaluate_colors=evaluate_colors, tile_size=int(tile_size), **options)
    cursor = color_dims
    channels = {"color": slice(0, color_dims), "depth": None, "normal": None, "extra": None}
    if render_depth:
        channels["depth"] = slice(cursor, cursor + 1)
        cursor += 1
    if render_normals:
        channels["normal"] = slice(cursor, cursor + 3)
        cursor += 3
    if extra is not None:
        channels["extra"] = slice(cursor, cursor + extra.shape[1])
        cursor += extra.shape[1]
    meta["channels"] = channels
    meta["backend"] = backend
    if meta["means2d"].requires_grad:
        meta["means2d"].retain_grad()
    return render, alpha, meta
