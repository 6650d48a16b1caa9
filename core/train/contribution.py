"""Which Gaussians the training views can see.

A Gaussian's *blending weight* at a pixel is what it adds to that pixel's colour per unit of
its own colour: its alpha there times the transmittance left in front of it. Summed over a
view's pixels it is how many pixels' worth of the image the Gaussian paints. Divided by its
*footprint* (the same sum with nothing in front: its opacity times the area of its projected
Gaussian, 2 pi sqrt(det) of the 2D covariance) it is the share of light that reaches it in
that view: about 1 for a Gaussian in the open, about 0 for one behind an opaque surface.

A Gaussian that almost no light reaches in any training view is hidden: the photometric loss
cannot move it, so wherever densification left it (split children below the surface, clones
behind a crater rim), it stays, and as an opaque point it still counts in the exported point
cloud and in its distances to the terrain. Pruning by visibility is an established step of
3DGS simplification (LightGaussian and Mini-Splatting score Gaussians by their blending
weights); the share of light, rather than the weight alone, keeps the many small Gaussians
that do show: a weight threshold in pixels pruned those too and cost 1-5 dB on a
320x180 outdoor scene (docs/training.md).

The weights come from one backward pass per view: render every Gaussian with colour 1 (one
channel, no background, no sky); the gradient of the image's sum with respect to each
Gaussian's colour is exactly its summed blending weight, on every backend.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Iterable

import torch

from ..render.constants import ALPHA_MAX, FAR_PLANE, NEAR_PLANE
from ..render.projection import project_gaussians
from .gaussians import RenderParams

#: render(params, view) -> image [H, W, C] of raw colour features, no background
Render = Callable[[RenderParams, object], torch.Tensor]
#: camera(view) -> (viewmat [4, 4] world-to-camera, K [3, 3], width, height)
Camera = Callable[[object], tuple[torch.Tensor, torch.Tensor, int, int]]


@dataclass
class Visibility:
    """Per Gaussian, over the training views: ``weight`` [N] the largest summed blending weight
    in one view (pixels); ``seen`` [N] whether its centre falls inside some view's image;
    ``light`` [N] the largest share of light reaching it (0-1) over the views whose image holds
    its centre (0 where none does)."""

    weight: torch.Tensor
    seen: torch.Tensor
    light: torch.Tensor

    def hidden(self, threshold: float) -> torch.Tensor:
        """[N] bool: inside some training image, yet less than ``threshold`` of the light reaches
        it in every one. Gaussians outside every training image are not hidden, only unseen:
        they keep what initialisation gave them (SfM points beyond the training views' edges
        that held-out views may show)."""
        return self.seen & (self.light < threshold)


def footprint(projected: dict, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(area [N], on_screen [N] bool)`` of one camera's projected Gaussians (the dict of
    :func:`~esgs.core.render.projection.project_gaussians`, camera axis dropped).

    ``area``: the summed alpha of each Gaussian with nothing in front, in pixels: its opacity
    (clamped as alphas are, at 0.99: even an opaque Gaussian passes 1 % of the light) times
    the integral of exp(-d^T C d / 2), 2 pi / sqrt(det C), times the share of it inside the
    image (per axis from the marginal standard deviations, exact for axis-aligned ellipses).
    ``on_screen``: in front of the camera with the centre inside the image.
    """
    a, b, c = projected["conics"].unbind(-1)
    area = projected["opacities"].clamp(max=ALPHA_MAX) * (2.0 * math.pi) / torch.sqrt((a * c - b * b).clamp_min(1e-30))
    sigma = projected["cov_diagonal"].to(area).clamp_min(1e-12).sqrt()
    u, v = projected["means2d"].detach().to(area).unbind(-1)

    def inside(centre: torch.Tensor, deviation: torch.Tensor, size: int) -> torch.Tensor:
        normal = torch.distributions.Normal(centre, deviation)
        return normal.cdf(torch.full_like(centre, float(size))) - normal.cdf(torch.zeros_like(centre))

    area = area * inside(u, sigma[:, 0], width) * inside(v, sigma[:, 1], height)
    valid = projected["valid"]
    on_screen = valid & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    return torch.where(valid, area, torch.zeros_like(area)), on_screen


def training_visibility(params: RenderParams, views: Iterable, render: Render, camera: Camera, *,
                        antialiased: bool = False, eps2d: float = 0.3) -> Visibility:
    """:class:`Visibility` of ``params`` over ``views`` (see the module's docstring).

    ``render`` draws with the run's backend; ``antialiased``/``eps2d`` must be the ones it
    renders with (the footprint is the same projected Gaussian). The geometry of ``params``
    is detached: nothing here reaches the optimiser.
    """
    count = params.means.shape[0]
    device = params.means.device
    geometry = replace(params, means=params.means.detach(), quats=params.quats.detach(),
                       scales=params.scales.detach(), opacities=params.opacities.detach(), extra=None)
    weight_peak = torch.zeros(count, device=device, dtype=torch.float32)
    light_peak = torch.zeros(count, device=device, dtype=torch.float32)
    seen = torch.zeros(count, device=device, dtype=torch.bool)
    for view in views:
        ones = torch.ones(count, 1, device=device, dtype=params.means.dtype, requires_grad=True)
        image = render(replace(geometry, colors=ones, sh_degree=None), view)
        (weights,) = torch.autograd.grad(image.sum(), ones, allow_unused=True)
        if weights is None:
            continue
        weights = weights[:, 0].detach().float()
        with torch.no_grad():
            viewmat, K, width, height = camera(view)
            projected = project_gaussians(geometry.means, geometry.quats, geometry.scales, geometry.opacities,
                                          viewmat.to(geometry.means)[None], K.to(geometry.means)[None], width, height,
                                          near_plane=NEAR_PLANE, far_plane=FAR_PLANE, antialiased=antialiased,
                                          eps2d=eps2d, need_normals=False)
            area, on_screen = footprint({name: value[0] for name, value in projected.items()
                                         if isinstance(value, torch.Tensor)}, width, height)
            area = area.float()
            light = torch.where(on_screen & (area > 0), weights / area.clamp_min(1e-12), torch.zeros_like(weights))
        weight_peak = torch.maximum(weight_peak, weights)
        light_peak = torch.maximum(light_peak, light.clamp(max=1.0))
        seen |= on_screen
    return Visibility(weight=weight_peak, seen=seen, light=light_peak)
