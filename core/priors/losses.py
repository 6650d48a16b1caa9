"""Geometry-prior loss terms of ESGS: depth, normal and depth-normal consistency.

All terms are plain differentiable torch functions on one view:

- rendered maps come from the rasterizer (expected depth [H,W], normals [H,W,3] in the camera
  frame, OpenCV axes, not renormalised) and alpha [H,W];
- prior maps come from ``priors/<source>/`` (depth [H,W] along the camera z axis, normals
  [H,W,3] camera frame, mask [H,W] bool: True where the prior is valid surface).

Edge-aware weighting ``exp(-edge_strength * |grad I|)`` makes the priors pull hard where the
image is flat (textureless sand, where photometry says little) and give way where the image
has texture, where the photometric loss knows better. Pixels outside the mask (sky, horizon,
beyond a depth limit, no prior) never contribute: this is the sky fix for the failure the
paper reports at the terrain/sky boundary.
"""
from __future__ import annotations

import torch

_EPS = 1e-6


def image_gradient_magnitude(image: torch.Tensor) -> torch.Tensor:
    """|grad I| of an image [H,W,C] or [H,W] -> [H,W], mean over channels, forward differences
    (replicated at the last row/column)."""
    if image.dim() == 3:
        image = image.mean(dim=-1)
    dx = torch.zeros_like(image)
    dy = torch.zeros_like(image)
    dx[:, :-1] = (image[:, 1:] - image[:, :-1]).abs()
    dy[:-1, :] = (image[1:, :] - image[:-1, :]).abs()
    dx[:, -1] = dx[:, -2] if image.shape[1] > 1 else 0
    dy[-1, :] = dy[-2, :] if image.shape[0] > 1 else 0
    return torch.sqrt(dx * dx + dy * dy)


def edge_aware_weights(image: torch.Tensor, edge_strength: float = 10.0) -> torch.Tensor:
    """Per-pixel prior weights [H,W] in (0, 1]: 1 on flat image regions, small on edges.

    ``image`` [H,W,3] (or [H,W]) in [0, 1]; no gradient flows into the image.
    """
    with torch.no_grad():
        return torch.exp(-edge_strength * image_gradient_magnitude(image))


def _masked_mean(values: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    total = weights.sum()
    if total <= 0:
        return values.sum() * 0.0  # keeps the graph, contributes nothing
    return (values * weights).sum() / total


def fit_scale_shift(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                    iterations: int = 10, huber_delta: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Robust (s, t) minimising |s * pred + t - target| over ``mask`` (no gradient).

    Least squares first, then iteratively re-weighted least squares with Huber weights, so a
    few outliers (sky leaking into a prior, wrong SfM points) do not drag the fit. ``pred``,
    ``target`` [H,W] (or any shape), ``mask`` bool of the same shape. Returns scalars.
    """
    with torch.no_grad():
        x = pred[mask].double()
        y = target[mask].double()
        if x.numel() < 2:
            return torch.ones((), dtype=pred.dtype), torch.zeros((), dtype=pred.dtype)
        w = torch.ones_like(x)
        scale = torch.ones((), dtype=torch.float64)
        shift = torch.zeros((), dtype=torch.float64)
        for _ in range(max(1, iterations)):
            sw = w.sum()
            mx = (w * x).sum() / sw
            my = (w * y).sum() / sw
            var = (w * (x - mx) ** 2).sum()
            if var <= 1e-18:
                scale = torch.ones((), dtype=torch.float64)
                shift = my - mx
            else:
                scale = (w * (x - mx) * (y - my)).sum() / var
                shift = my - scale * mx
            residual = (scale * x + shift - y).abs()
            delta = huber_delta if huber_delta is not None else 1.4826 * residual.median() + 1e-12
            w = torch.where(residual <= delta, torch.ones_like(residual), delta / residual)
        return scale.to(pred.dtype), shift.to(pred.dtype)


def depth_loss(rendered_depth: torch.Tensor, prior_depth: torch.Tensor, mask: torch.Tensor,
               weights: torch.Tensor | None = None, *, mode: str = "log", relative: bool = False,
               alpha: torch.Tensor | None = None, confidence: torch.Tensor | None = None,
               robust: float = 0.0) -> torch.Tensor:
    """Edge-aware depth loss of one view.

    ``mode`` "log": L1 of log depth (scale-free errors: a 10 cm miss at 2 m counts like 1 m at
    20 m, which suits rover views spanning near and far range); "inverse": L1 of inverse depth
    (far range, where priors are least reliable, weighs least). With ``relative`` the prior is
    only known up to scale and shift (NDN output, relative labels): the prior is first aligned
    to the rendered depth with :func:`fit_scale_shift` (in inverse depth for "inverse", depth
    otherwise), without gradient through the fit. ``alpha`` [H,W], when given, restricts the
    loss to pixels the Gaussians actually cover (alpha > 0.5). ``confidence`` [H,W] in [0, 1]
    scales each pixel's error without renormalising: a view trusted half as much pulls half as
    hard (the edge weights, in contrast, only redistribute the pull within the view).
    ``robust`` > 0: each pixel's error e counts as ``robust * log(1 + e / robust)``, so a pixel
    pulls with 1 / (1 + e / robust) of the L1 pull: a prior pixel far from the render (likely
    a wrong prior) pulls little, close ones as before (0 = plain L1).
    """
    valid = mask & (prior_depth > 0) & (rendered_depth > 0)
    if alpha is not None:
        valid = valid & (alpha > 0.5)
    weights = torch.ones_like(rendered_depth) if weights is None else weights
    prior = prior_depth
    if mode == "log":
        if relative:
            scale, shift = fit_scale_shift(prior, rendered_depth.detach(), valid)
            prior = scale * prior + shift
            valid = valid & (prior > 0)
        safe_rendered = torch.where(valid, rendered_depth, torch.ones_like(rendered_depth))
        safe_prior = torch.where(valid, prior, torch.ones_like(prior))
        error = (torch.log(safe_rendered) - torch.log(safe_prior)).abs()
    elif mode == "inverse":
        inverse_rendered = 1.0 / rendered_depth.clamp_min(_EPS)
        inverse_prior = 1.0 / prior.clamp_min(_EPS)
        if relative:
            scale, shift = fit_scale_shift(inverse_prior, inverse_rendered.detach(), valid)
            inverse_prior = scale * inverse_prior + shift
        error = (inverse_rendered - inverse_prior).abs()
    else:
        raise ValueError(f"unknown depth loss mode {mode!r} (use 'log' or 'inverse')")
    if robust > 0:
        error = robust * torch.log1p(error / robust)
    error = torch.where(valid, error, torch.zeros_like(error))
    if confidence is not None:
        error = error * confidence
    return _masked_mean(error, weights * valid)


def incidence_weights(prior_normal: torch.Tensor, K: torch.Tensor, cosine: float) -> torch.Tensor:
    """[H, W] weights ``min(1, (|n . r| / cosine)^2)`` of a view's depth-prior pixels.

    A depth prior that comes from a surface estimate (a rebuilt mesh, a predicted height
    field) errs along the ray by its error across the surface over ``|n . r|``, the cosine
    between the unit ray ``r`` and the surface normal ``n``: where a ray grazes the surface a
    small error in height is a large error in depth. Weighting each pixel by the inverse of
    that growth squared (as an inverse variance), from ``cosine`` down, keeps the prior's pull
    where it is accurate. prior_normal: [H, W, 3] camera-frame normals (zero-length: unknown,
    weight 1); K: [3, 3]; ``cosine`` > 0.
    """
    from ..render.surface import pixel_rays  # here: this module stays torch-only (render loads the rasterizers)

    height, width = prior_normal.shape[:2]
    rays = pixel_rays(K.to(prior_normal), width, height)
    rays = rays / rays.norm(dim=-1, keepdim=True)
    length = prior_normal.norm(dim=-1)
    cos = (rays * prior_normal).sum(-1).abs() / length.clamp_min(_EPS)
    weights = (cos / cosine).clamp(max=1.0) ** 2
    return torch.where(length > _EPS, weights, torch.ones_like(weights))


def normal_loss(rendered_normal: torch.Tensor, prior_normal: torch.Tensor, mask: torch.Tensor,
                weights: torch.Tensor | None = None, alpha: torch.Tensor | None = None,
                confidence: torch.Tensor | None = None) -> torch.Tensor:
    """Edge-aware normal loss of one view: L1 plus (1 - cos) between unit normals.

    ``rendered_normal`` [H,W,3] is renormalised here (the rasterizer composites normals like a
    colour); pixels with a zero-length rendered or prior normal are skipped. ``confidence``
    scales each pixel's error as in :func:`depth_loss`.
    """
    rendered_length = rendered_normal.norm(dim=-1)
    prior_length = prior_normal.norm(dim=-1)
    valid = mask & (rendered_length > 1e-3) & (prior_length > 0.5)
    if alpha is not None:
        valid = valid & (alpha > 0.5)
    weights = torch.ones_like(rendered_length) if weights is None else weights
    unit_rendered = rendered_normal / rendered_length.clamp_min(1e-3).unsqueeze(-1)
    unit_prior = prior_normal / prior_length.clamp_min(1e-6).unsqueeze(-1)
    l1 = (unit_rendered - unit_prior).abs().sum(dim=-1)
    angular = 1.0 - (unit_rendered * unit_prior).sum(dim=-1)
    error = torch.where(valid, l1 + angular, torch.zeros_like(l1))
    if confidence is not None:
        error = error * confidence
    return _masked_mean(error, weights * valid)


def thinness_loss(thickness: torch.Tensor, prior_normal: torch.Tensor, mask: torch.Tensor,
                  weights: torch.Tensor | None = None, confidence: torch.Tensor | None = None) -> torch.Tensor:
    """Normal prior on each pixel's surface Gaussian: the mean of its thickness along the prior
    normal (:func:`~esgs.core.render.surface.median_surface_thinness`, [H,W]) over the pixels of
    ``mask`` with a prior normal, edge-weighted like :func:`normal_loss`; ``confidence`` scales
    each pixel's value."""
    valid = mask & (prior_normal.norm(dim=-1) > 0.5)
    weights = torch.ones_like(thickness) if weights is None else weights
    error = torch.where(valid, thickness, torch.zeros_like(thickness))
    if confidence is not None:
        error = error * confidence
    return _masked_mean(error, weights * valid)


def sky_loss(rendered_depth: torch.Tensor, alpha: torch.Tensor, sky: torch.Tensor,
             far_depth: torch.Tensor | float) -> torch.Tensor:
    """Push what the Gaussians draw over sky pixels beyond the scene's far surface.

    ``rendered_depth`` [H,W] expected depth, ``alpha`` [H,W] coverage, ``sky`` [H,W] bool
    (pixels with no surface along the ray), ``far_depth`` the view's farthest surface distance.
    The loss is the mean over sky pixels of ``alpha * relu(log far - log depth)``: zero where the
    sky is empty (alpha 0) or drawn at least as far as the far surface, so it never fights a
    sky painted by distant Gaussians. One-sided on purpose: sky has no true depth to match,
    only a lower bound. ``alpha`` is a weight, not a target (no gradient reaches it): the
    Gaussians that paint the sky are moved back, never made transparent, because a transparent
    sky shows the background colour and the photometric loss then fights the prior (measured on
    rover_horizon, docs/esgs.md "The sky loss": with the gradient through alpha the sky went
    transparent and held-out PSNR fell by 2.3 dB at weight 0.3; without it PSNR is unchanged).
    """
    count = sky.sum()
    if int(count) == 0:
        return rendered_depth.sum() * 0.0
    far = torch.as_tensor(far_depth, dtype=rendered_depth.dtype, device=rendered_depth.device)
    log_depth = torch.log(rendered_depth.clamp_min(_EPS))
    shortfall = torch.relu(torch.log(far.clamp_min(_EPS)) - log_depth)
    return torch.where(sky, alpha.detach() * shortfall, torch.zeros_like(shortfall)).sum() / count


def normals_from_depth(depth: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-frame unit normals [H,W,3] from a depth map [H,W] and intrinsics K [3,3].

    Back-projects every pixel (centres at +0.5) and crosses central differences; normals face
    the camera (negative z in OpenCV axes). Also returns a validity mask [H,W] (interior pixels
    whose 4 neighbours have depth > 0).
    """
    height, width = depth.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    v, u = torch.meshgrid(torch.arange(height, dtype=depth.dtype), torch.arange(width, dtype=depth.dtype),
                          indexing="ij")
    points = torch.stack([(u + 0.5 - cx) / fx * depth, (v + 0.5 - cy) / fy * depth, depth], dim=-1)
    dx = torch.zeros_like(points)
    dy = torch.zeros_like(points)
    dx[:, 1:-1] = points[:, 2:] - points[:, :-2]
    dy[1:-1, :] = points[2:, :] - points[:-2, :]
    normal = torch.cross(dx, dy, dim=-1)
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # face the camera: the viewing ray is +z-ish, a visible surface's normal has n . p < 0
    facing = (normal * points).sum(-1, keepdim=True)
    normal = torch.where(facing > 0, -normal, normal)
    positive = depth > 0
    valid = torch.zeros_like(positive)
    valid[1:-1, 1:-1] = (positive[1:-1, 1:-1] & positive[1:-1, 2:] & positive[1:-1, :-2]
                         & positive[2:, 1:-1] & positive[:-2, 1:-1])
    return normal, valid


def depth_normal_consistency_loss(rendered_depth: torch.Tensor, rendered_normal: torch.Tensor, K: torch.Tensor,
                                  mask: torch.Tensor | None = None, weights: torch.Tensor | None = None) -> torch.Tensor:
    """1 - cos between normals derived from the rendered depth and the rendered normals [H,W,3].

    Ties each Gaussian's orientation to the surface its depth describes (as 2DGS/PGSR do).
    """
    depth_normal, valid = normals_from_depth(rendered_depth, K)
    length = rendered_normal.norm(dim=-1)
    valid = valid & (length > 1e-3)
    if mask is not None:
        valid = valid & mask
    unit = rendered_normal / length.clamp_min(1e-3).unsqueeze(-1)
    error = 1.0 - (unit * depth_normal).sum(dim=-1)
    weights = torch.ones_like(error) if weights is None else weights
    return _masked_mean(torch.where(valid, error, torch.zeros_like(error)), weights * valid)
