"""CUDA backend: a thin mapping onto ``gsplat.rasterization`` (optional dependency).

gsplat is imported only when this backend is asked for. Mapping:
- colour, normals and extra are concatenated into one per-camera feature tensor
  ``[C, N, D + 3 + E]``: colours are evaluated here (our SH, same as the other backends),
  so gsplat runs with ``sh_degree=None``; normals are our camera-frame shortest axes.
- ``render_depth`` -> ``render_mode="RGB+ED"`` (gsplat's expected depth is sum(w z) /
  sum(w), like ours; it comes as the last channel and is moved behind the colours).
- ``antialiased`` -> ``rasterize_mode="antialiased"`` with the same ``eps2d``; classic mode
  is gsplat's default, which also dilates by 0.3 px^2.
- ``backgrounds`` are padded with zeros for the non-colour channels.
Not matched exactly: gsplat culls with a 3-sigma radius instead of our opacity-aware one,
and clamps the Jacobian with its own margin, so results agree to rendering accuracy, not
bit for bit. Checked on an H200 against the CPU backend by ``benchmarks/bench_cuda.py``
(docs/benchmarks.md): renders agree to ~1e-7, gradients to cosine similarity > 0.99999.
"""
from __future__ import annotations

import torch

from ..errors import ConfigError
from . import constants as K
from .projection import project_gaussians


def cuda_available() -> tuple[bool, str]:
    """(available, reason) for the gsplat CUDA backend."""
    if not torch.cuda.is_available():
        return False, "torch reports no CUDA device"
    try:
        import gsplat  # noqa: F401
    except ImportError as error:  # optional dependency
        return False, f"gsplat is not installed ({error})"
    return True, ""


def rasterize_cuda(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, near_plane, far_plane,
                   sh_degree, backgrounds, render_depth, render_normals, extra, antialiased, eps2d, tile_size,
                   evaluate_colors):
    """See :func:`esgs.core.render.rasterization`; returns (render, alpha, meta)."""
    available, reason = cuda_available()
    if not available:
        raise ConfigError(f"the cuda rasterizer backend is unavailable: {reason}",
                          hint='use backend="cpu", or install gsplat on a CUDA machine')
    import gsplat

    cameras = viewmats.shape[0]
    pieces = [torch.stack([evaluate_colors(cam) for cam in range(cameras)])]
    color_dims = pieces[0].shape[-1]
    if render_normals:
        projected = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height,
                                      near_plane=near_plane, far_plane=far_plane, antialiased=antialiased,
                                      eps2d=eps2d, need_normals=True)
        pieces.append(projected["normals"])
    if extra is not None:
        pieces.append(extra[None].expand(cameras, -1, -1))
    features = torch.cat(pieces, dim=-1)
    if backgrounds is not None:
        backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(cameras, features.shape[-1] - color_dims)], -1)
    render, alpha, meta = gsplat.rasterization(
        means, quats, scales, opacities, features, viewmats, Ks, width, height,
        near_plane=near_plane, far_plane=far_plane, sh_degree=None, backgrounds=backgrounds,
        render_mode="RGB+ED" if render_depth else "RGB", rasterize_mode="antialiased" if antialiased else "classic",
        # gsplat's classic mode dilates by eps2d too: give it the fixed 3DGS dilation the cpu and
        # reference backends use, so a 3DGS run means the same on every backend
        eps2d=eps2d if antialiased else K.CLASSIC_DILATION, tile_size=tile_size, packed=False)
    if render_depth:
        depth = render[..., -1:]
        render = torch.cat([render[..., :color_dims], depth, render[..., color_dims:-1]], dim=-1)
    radii = meta["radii"]
    if radii.dim() == 3:  # gsplat >= 1.5 gives per-axis radii
        radii = radii.max(dim=-1).values
    out_meta = {"means2d": meta["means2d"], "radii": radii.int(), "depths": meta["depths"], "gsplat_meta": meta}
    return render, alpha, out_meta
