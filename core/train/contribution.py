"""How much each Gaussian shows in the training views.

A Gaussian's *blending weight* at a pixel is what it adds to that pixel's colour per unit of
its own colour: its alpha times the transmittance left in front of it. Summed over a view's
pixels it says how many pixels' worth of the image the Gaussian paints there. A Gaussian
whose sum stays below a pixel or so in every training view is hidden (behind the surface,
inside another Gaussian) or negligible: the photometric loss barely constrains it, so
wherever densification left it, it stays, yet as an opaque point it still counts in the
exported point cloud and its distances to the terrain. Pruning such Gaussians is the
"contribution" pruning of LightGaussian / RadSplat-style methods, written here for our
rasterizer.

The weights come from one backward pass per view: render every Gaussian with colour 1
(one channel, no background, no sky); the gradient of the image's sum with respect to each
Gaussian's colour is exactly that Gaussian's summed blending weight, on every backend.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable, Iterable

import torch

from .gaussians import RenderParams


def blend_weight_peaks(params: RenderParams, views: Iterable, render: Callable[[RenderParams, object], torch.Tensor]
                       ) -> torch.Tensor:
    """[N] each Gaussian's largest summed blending weight (in pixels) over ``views``.

    ``render(params, view)`` returns the rendered image [H, W, C] of ``params`` in ``view``
    (colours are raw features, ``sh_degree`` None); it must not add a background. The
    geometry of ``params`` is detached: nothing here reaches the optimiser.
    """
    count = params.means.shape[0]
    device = params.means.device
    geometry = replace(params, means=params.means.detach(), quats=params.quats.detach(),
                       scales=params.scales.detach(), opacities=params.opacities.detach(), extra=None)
    peaks = torch.zeros(count, device=device, dtype=torch.float32)
    for view in views:
        ones = torch.ones(count, 1, device=device, dtype=params.means.dtype, requires_grad=True)
        image = render(replace(geometry, colors=ones, sh_degree=None), view)
        (weights,) = torch.autograd.grad(image.sum(), ones, allow_unused=True)
        if weights is not None:
            peaks = torch.maximum(peaks, weights[:, 0].detach().float())
    return peaks
