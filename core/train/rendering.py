"""Render one training view from :class:`RenderParams` through the project's rasterizer."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import torch

from .gaussians import RenderParams


def resolve_backend(backend: str) -> str:
    """"auto" -> "cuda" when a CUDA device and gsplat are usable, else "cpu"."""
    if backend != "auto":
        return backend
    if torch.cuda.is_available():
        import importlib.util

        if importlib.util.find_spec("gsplat") is not None:
            return "cuda"
    return "cpu"


def backend_device(backend: str) -> torch.device:
    return torch.device("cuda") if backend == "cuda" else torch.device("cpu")


@dataclass
class RenderOutput:
    """One rendered view, channels split out.

    image [H, W, 3]; alpha [H, W, 1]; depth [H, W, 1] expected camera-z depth (None unless
    requested); normals [H, W, 3] camera frame, not renormalised (None unless requested);
    extra [H, W, E] or None; meta: the rasterizer's meta (means2d [1, N, 2] with its
    gradient after backward, radii [1, N]).
    """

    image: torch.Tensor
    alpha: torch.Tensor
    depth: Optional[torch.Tensor]
    normals: Optional[torch.Tensor]
    extra: Optional[torch.Tensor]
    meta: dict


def render_view(params: RenderParams, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, *,
                background: Optional[torch.Tensor] = None, render_depth: bool = False, render_normals: bool = False,
                backend: str = "cpu", num_threads: Optional[int] = None, antialiased: bool = False,
                eps2d: float = 0.3, sky: Any = None) -> RenderOutput:
    """Render ``params`` into one camera. viewmat: [4, 4] world-to-camera; K: [3, 3]; background: [3].

    ``antialiased``/``eps2d``: the rasterizer's 2D anti-aliasing filter (Mip-Splatting's 2D filter).
    ``sky``: a :class:`~.sky.SkyModel` composited behind the Gaussians (``background`` is then unused).
    """
    from ..render import rasterization

    if sky is not None:
        background = None  # the Gaussians on black, then the sky where they leave the pixel transparent

    render, alpha, meta = rasterization(
        params.means, params.quats, params.scales, params.opacities, params.colors,
        viewmat[None], K[None], width, height, sh_degree=params.sh_degree,
        backgrounds=None if background is None else background[None],
        render_depth=render_depth, render_normals=render_normals, extra=params.extra,
        num_threads=num_threads, backend=backend, antialiased=antialiased, eps2d=eps2d)
    channels = meta["channels"]

    def part(name: str) -> Optional[torch.Tensor]:
        piece = channels.get(name)
        return None if piece is None else render[0, :, :, piece]

    image = part("color")
    if sky is not None:
        from .sky import composite

        image = composite(image, alpha[0], sky.image(viewmat, K, width, height).to(image))
    return RenderOutput(image=image, alpha=alpha[0], depth=part("depth"), normals=part("normal"),
                        extra=part("extra"), meta=meta)
