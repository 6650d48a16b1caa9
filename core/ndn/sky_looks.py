"""New skies for NDN training triples: the sky head learns where the sky is, not its colour.

The generator paints every sky the same way: a smooth gradient of middle brightness, close to
the ground's, in a colour drawn per scene. A network trained on it marks sky by colour and finds none
in real grey frames, where the sky is the brightest, flattest part of the image and is often
clipped white near the sun (Curiosity's Navcam: docs/ndn.md). :func:`relight_sky` repaints the
sky pixels of a training triple with a sky drawn at random: any brightness from dim to clipped
white, grey or tinted, a gradient towards the horizon, sometimes a glare patch and a little
noise. The ground, depth, normals and evidence stay as they were.

A triple's three views keep one sky colour (one camera, one exposure), so the sky stays
consistent between the views the network compares; each view has its own gradient and glare
(the views point in different directions). The sky pixels of the two neighbour views are
known because each neighbour is another view of the same scene and so the centre of another
triple in the same shard (:func:`sky_of_views`).
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = ["sky_of_views", "relight_sky"]


def sky_of_views(views: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sky of each view of one shard's triples: ``(sky [N, 3, h, w] bool, known [N] bool)``.

    ``views`` [N, 9, h, w] (centre, neighbour 1, neighbour 2) and ``mask`` [N, h, w] (surface of
    the centre view) are one shard's arrays. A neighbour's sky is the mask of the triple whose
    centre image is byte-identical to it; a triple with a neighbour found nowhere in the shard
    is not ``known`` (its neighbours' sky stays False) and is never relit.
    """
    count = len(views)
    sky = np.zeros((count, 3, *views.shape[-2:]), bool)
    sky[:, 0] = ~mask.astype(bool)
    centres = {views[index, :3].tobytes(): index for index in range(count)}
    known = np.ones(count, bool)
    for index in range(count):
        for slot in (1, 2):
            match = centres.get(views[index, 3 * slot:3 * slot + 3].tobytes())
            if match is None:
                known[index] = False
            else:
                sky[index, slot] = ~mask[match].astype(bool)
    return sky, known


def relight_sky(views: torch.Tensor, sky: torch.Tensor, generator: torch.Generator, *,
                probability: float) -> torch.Tensor:
    """Repaint the sky of each triple with probability ``probability`` (views in [-1, 1]).

    ``views`` [B, 9, h, w]; ``sky`` [B, 3, h, w] bool (False everywhere for a triple whose
    neighbours' sky is unknown, which is then left alone). Draws from ``generator`` in a fixed
    order whatever the masks hold, so a resumed run repeats an uninterrupted one. Returns a new
    tensor; pixels outside the sky are returned unchanged, bit for bit.
    """
    batch, _, height, width = views.shape
    chosen = torch.rand(batch, generator=generator) < probability
    brightness = 0.3 + 0.7 * torch.rand(batch, generator=generator)  # dim haze to clipped white
    tint = (torch.rand((batch, 3), generator=generator) - 0.5) * 0.6 * torch.rand((batch, 1), generator=generator)
    slope = (torch.rand((batch, 3), generator=generator) - 0.5) * 0.6  # brightness change, top to bottom
    glare = (torch.rand((batch, 3), generator=generator) < 0.3).float() * (0.2 + 0.6 * torch.rand((batch, 3),
                                                                                              generator=generator))
    centre = torch.rand((batch, 3, 2), generator=generator)
    radius = 0.15 + 0.45 * torch.rand((batch, 3), generator=generator)
    noise = 0.02 * torch.randn((batch, 3, 3, height, width), generator=generator)

    rows = torch.linspace(0.0, 1.0, height).view(1, 1, height, 1)
    columns = torch.linspace(0.0, 1.0, width).view(1, 1, 1, width)
    aspect = width / height
    distance = torch.sqrt(((columns - centre[..., 0, None, None]) * aspect) ** 2
                          + (rows - centre[..., 1, None, None]) ** 2)  # [B, 3, h, w], in heights
    level = (brightness[:, None, None, None] + slope[..., None, None] * (rows - 0.5)
             + glare[..., None, None] * torch.exp(-0.5 * (distance / radius[..., None, None]) ** 2))
    colour = level[:, :, None] * (1.0 + tint[:, None, :, None, None]) + noise  # [B, 3 views, 3 channels, h, w]
    new = colour.clamp(0.0, 1.0) * 2.0 - 1.0
    replace = (sky & chosen[:, None, None, None])[:, :, None].expand_as(new)
    result = torch.where(replace, new.to(views.dtype), views.reshape(batch, 3, 3, height, width))
    return result.reshape(views.shape)
