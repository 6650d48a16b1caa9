"""Which pixels of a view show ground that no training view saw.

A held-out view can look at ground outside every training image (behind a ridge, past the
training drive's end). No method can reconstruct it, and without a mark a reader takes the
sky colour or the hole there for an error of the method. :func:`unseen_ground` finds those
pixels from the trained Gaussians alone, so it works on real scenes without ground truth:

1. render the view's expected depth and alpha; pixels with alpha >= ``min_alpha`` are
   surface, lifted to world points with the view's intrinsics and pose. Ground no training
   view saw is often rendered thin (low alpha, the sky model showing through), so when the
   scene has true depth (synthetic scenes: ``priors/gt``) the caller passes it instead and
   every pixel its mask calls surface is tested;
2. render each training view's depth once and project every point into it: the point is
   seen when it lands inside that image, in front of the camera, and within
   ``depth_tolerance`` (relative) of the depth the training view renders there (so ground
   hidden behind nearer relief in that view does not count);
3. unseen ground = surface pixels seen by no training view.
"""
from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np
import torch

from .dataset import View


def _render_depth(params: Any, view: View, *, backend: str, device: torch.device,
                  num_threads: Optional[int]) -> tuple[torch.Tensor, torch.Tensor]:
    from .rendering import render_view

    output = render_view(params, view.viewmat.to(device), view.K.to(device), view.width, view.height,
                         render_depth=True, backend=backend, num_threads=num_threads)
    return output.depth[..., 0].float().cpu(), output.alpha[..., 0].float().cpu()


def unseen_ground(params: Any, view: View, train_views: Sequence[View], *, backend: str = "cpu",
                  device: torch.device | str = "cpu", min_alpha: float = 0.5, depth_tolerance: float = 0.05,
                  num_threads: Optional[int] = None,
                  train_depths: Optional[list[tuple[torch.Tensor, torch.Tensor]]] = None,
                  depth: Optional[np.ndarray] = None, surface: Optional[np.ndarray] = None) -> np.ndarray:
    """[H, W] bool: surface pixels of ``view`` that none of ``train_views`` sees.

    ``params``: the run's :class:`~.gaussians.RenderParams`. ``train_depths``: the training
    views' rendered (depth, alpha), when the caller has them already (one render per view
    serves every held-out view). ``depth`` [H, W] and ``surface`` [H, W] bool: the view's true
    depth and surface mask, used instead of its rendered depth when given.
    """
    device = torch.device(device)
    with torch.no_grad():
        if depth is not None:
            depth = torch.as_tensor(np.asarray(depth, dtype=np.float32))
            valid = torch.as_tensor(np.asarray(surface, dtype=bool)) if surface is not None else torch.ones_like(depth, dtype=torch.bool)
            surface = valid & (depth > 0)
        else:
            depth, alpha = _render_depth(params, view, backend=backend, device=device, num_threads=num_threads)
            surface = (alpha >= min_alpha) & (depth > 0)
        rows, cols = torch.nonzero(surface, as_tuple=True)
        if len(rows) == 0:
            return np.zeros((view.height, view.width), dtype=bool)
        z = depth[rows, cols].double()
        K = view.K.double()
        x = (cols.double() + 0.5 - K[0, 2]) / K[0, 0] * z
        y = (rows.double() + 0.5 - K[1, 2]) / K[1, 1] * z
        camera = torch.stack([x, y, z, torch.ones_like(z)], dim=-1)
        world = camera @ torch.linalg.inv(view.viewmat.double()).T
        seen = torch.zeros(len(z), dtype=torch.bool)
        for index, train in enumerate(train_views):
            if train_depths is not None:
                train_depth, train_alpha = train_depths[index]
            else:
                train_depth, train_alpha = _render_depth(params, train, backend=backend, device=device,
                                                         num_threads=num_threads)
            local = world @ train.viewmat.double().T
            zt = local[:, 2]
            in_front = zt > 1e-6
            u = train.K[0, 0].double() * local[:, 0] / zt.clamp_min(1e-6) + train.K[0, 2].double()
            v = train.K[1, 1].double() * local[:, 1] / zt.clamp_min(1e-6) + train.K[1, 2].double()
            col, row = torch.floor(u).long(), torch.floor(v).long()
            inside = in_front & (col >= 0) & (col < train.width) & (row >= 0) & (row < train.height)
            if not bool(inside.any()):
                continue
            index_rows, index_cols = row[inside], col[inside]
            rendered = train_depth[index_rows, index_cols].double()
            hit = train_alpha[index_rows, index_cols] >= min_alpha
            close = (zt[inside] - rendered).abs() <= depth_tolerance * rendered.clamp_min(1e-6)
            seen[inside.nonzero(as_tuple=True)[0]] |= hit & close
        mask = np.zeros((view.height, view.width), dtype=bool)
        unseen = ~seen
        mask[rows[unseen].numpy(), cols[unseen].numpy()] = True
        return mask


def training_depths(params: Any, train_views: Sequence[View], *, backend: str = "cpu",
                    device: torch.device | str = "cpu",
                    num_threads: Optional[int] = None) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(depth, alpha) of every training view, rendered once for several :func:`unseen_ground` calls."""
    with torch.no_grad():
        return [_render_depth(params, view, backend=backend, device=torch.device(device), num_threads=num_threads)
                for view in train_views]
