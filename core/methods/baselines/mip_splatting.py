"""Mip-Splatting (Yu et al., CVPR 2024) as a trainer hook: the 3D smoothing filter.

Every Gaussian gets an isotropic 3D low-pass filter whose size matches the finest detail
the training cameras can resolve at its centre. The sampling rate of camera n at a point
at depth d is f_n / d (pixels per scene unit, f the focal length in pixels); a Gaussian's
maximal rate is the largest over the training cameras whose (slightly enlarged) frustum
contains its centre. The filter is a Gaussian of variance ``s / rate^2`` (s = 0.2) added
to the covariance; since it is isotropic, Sigma + v I keeps the rotation and each scale
becomes sqrt(scale^2 + v). The opacity is multiplied by sqrt(det Sigma / det(Sigma + v I))
so a filtered Gaussian keeps its integrated density. Rates depend only on the centres and
the cameras, so they are recomputed when the Gaussian set changes (densification) and
periodically while the centres move, not differentiated.

The 2D half of Mip-Splatting (a screen-space filter of ~one pixel with the same opacity
compensation) is the rasterizer's ``antialiased`` mode; the trainer turns it on for renders
and evaluation of the ``mip-splatting`` method (its RenderOptions).
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any, Optional, Sequence

import torch

from ...render.projection import project_points
from ...train.gaussians import GaussianModel, RenderParams
from ...train.hooks import RunView, StepContext, TrainHook
from .config import MipSplattingConfig

#: Centres closer than this to a camera (scene units) do not count as seen by it.
NEAR_PLANE = 0.01


def max_sampling_rate(means: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, widths: Sequence[int],
                      heights: Sequence[int], *, margin: float = 0.15,
                      near_plane: float = NEAR_PLANE) -> tuple[torch.Tensor, torch.Tensor]:
    """Largest sampling rate of every Gaussian centre over the cameras that see it.

    means: [N, 3]; viewmats: [C, 4, 4] world-to-camera (OpenCV axes); Ks: [C, 3, 3];
    widths/heights: C image sizes in pixels. A centre is seen by a camera when it lies in
    front of it (z > near_plane) and projects within the image enlarged by ``margin`` x its
    size on every side. The rate is max(fx, fy) / z (pixels per scene unit).

    Returns ``(rate [N], seen [N] bool)``. Centres seen by no camera get the smallest rate
    of the seen ones (the widest filter; 0 when nothing is seen at all).
    """
    means = means.detach()
    rate = torch.zeros(means.shape[0], dtype=means.dtype, device=means.device)
    seen = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
    for camera in range(viewmats.shape[0]):
        K = Ks[camera].to(means)
        u, v, safe_z, in_front = project_points(means, viewmats[camera], K, near_plane=near_plane)
        width, height = float(widths[camera]), float(heights[camera])
        inside = (in_front & (u >= -margin * width) & (u <= (1.0 + margin) * width)
                  & (v >= -margin * height) & (v <= (1.0 + margin) * height))
        camera_rate = torch.maximum(K[0, 0], K[1, 1]) / safe_z
        rate = torch.where(inside, torch.maximum(rate, camera_rate), rate)
        seen |= inside
    if bool(seen.any()):
        rate = torch.where(seen, rate, rate[seen].min())
    return rate, seen


def filter_variance(rate: torch.Tensor, strength: float = 0.2) -> torch.Tensor:
    """[N] variance ``strength / rate^2`` of the 3D filter (0 where the rate is 0: no camera at all)."""
    return torch.where(rate > 0, strength / rate.clamp_min(1e-12) ** 2, torch.zeros_like(rate))


def apply_3d_filter(scales: torch.Tensor, opacities: torch.Tensor,
                    variance: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Convolve each Gaussian with an isotropic Gaussian of ``variance``; differentiable.

    scales: [N, 3] activated standard deviations; opacities: [N]; variance: [N].
    Returns ``(scales [N, 3], opacities [N])``: sqrt(scale^2 + v) and
    opacity * sqrt(prod(scale^2) / prod(scale^2 + v)).
    """
    squared = scales * scales
    filtered = squared + variance.to(scales)[:, None]
    compensation = torch.sqrt(torch.prod(squared / filtered, dim=1))
    return torch.sqrt(filtered), opacities * compensation


def training_cameras(views: Sequence[Any]) -> tuple[torch.Tensor, torch.Tensor, list[int], list[int]]:
    """(viewmats [C, 4, 4], Ks [C, 3, 3], widths, heights) of dataset views."""
    viewmats = torch.stack([view.viewmat for view in views]).to(torch.float64)
    Ks = torch.stack([view.K for view in views]).to(torch.float64)
    return viewmats, Ks, [view.width for view in views], [view.height for view in views]


class MipSplattingHook(TrainHook):
    """Keeps each Gaussian's 3D filter variance and applies the filter before every render."""

    name = "baseline_mip_splatting"

    def __init__(self, config: MipSplattingConfig):
        self.config = config
        self.variance: Optional[torch.Tensor] = None
        self.refresh_every = 100

    def compute(self, run: RunView, means: Optional[torch.Tensor] = None) -> torch.Tensor:
        """The filter variance [N] of the current (or given) centres from the training cameras."""
        means = run.gaussians.params["means"] if means is None else means
        viewmats, Ks, widths, heights = training_cameras(run.train_views)
        rate, _ = max_sampling_rate(means.detach().to(torch.float64).cpu(), viewmats, Ks, widths, heights,
                                    margin=self.config.mip_frustum_margin)
        return filter_variance(rate, self.config.mip_filter_3d).to(torch.float32).to(means.device)

    def setup(self, run: RunView) -> None:
        # Mip-Splatting refreshes the rates every 100 of 30,000 steps; scaled like the other schedules
        self.refresh_every = run.scaled_step(100, minimum=1)
        self.variance = self.compute(run)

    def before_render(self, run: RunView, context: StepContext, params: RenderParams) -> Optional[RenderParams]:
        count = params.scales.shape[0]
        if self.variance is None or self.variance.shape[0] != count or context.step % self.refresh_every == 0:
            self.variance = self.compute(run)
        scales, opacities = apply_3d_filter(params.scales, params.opacities, self.variance)
        return replace(params, scales=scales, opacities=opacities)

    def model_params(self, run: RunView, params: RenderParams) -> RenderParams:
        """The model with the 3D filter of its current centres applied."""
        variance = self.variance if self.variance is not None and self.variance.shape[0] == params.scales.shape[0] \
            else self.compute(run)
        scales, opacities = apply_3d_filter(params.scales, params.opacities, variance)
        return replace(params, scales=scales, opacities=opacities)

    def on_densify(self, run: RunView, report: Any) -> None:
        if report.reset_opacity:
            return
        # centres of clones and split children differ from their sources: measure them again
        self.variance = self.compute(run)

    def export_model(self, run: RunView, gaussians: GaussianModel) -> GaussianModel:
        """A copy with the filter folded into scales and opacities (evaluation and the PLY)."""
        copy = type(gaussians).from_state_dict(gaussians.state_dict())
        copy.to(run.device)
        raw = copy.params
        with torch.no_grad():
            variance = self.compute(run, raw["means"])
            scales, opacities = apply_3d_filter(torch.exp(raw["log_scales"]),
                                                torch.sigmoid(raw["opacity_logit"]).reshape(-1), variance)
            opacities = opacities.clamp(1e-7, 1.0 - 1e-7)
            raw["log_scales"].copy_(torch.log(scales))
            raw["opacity_logit"].copy_(torch.log(opacities / (1.0 - opacities)).reshape(raw["opacity_logit"].shape))
        return copy

    def state_dict(self) -> dict:
        return {"variance": None if self.variance is None else self.variance.detach().cpu()}

    def load_state_dict(self, state: dict) -> None:
        variance = state.get("variance")
        if variance is not None:
            self.variance = variance
