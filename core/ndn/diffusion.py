"""DDPM forward process, training loss and deterministic DDIM sampling for the NDN network.

Both branches share one time step per sample: the depth state x_d [B, 1, H, W] and the
normal state x_n [B, 3, H, W] are noised with independent Gaussian noise at the same t and
denoised together.
"""
from __future__ import annotations

import math

import torch
from torch.nn import functional as F

from .config import NDNDiffusionConfig


def make_betas(timesteps: int, schedule: str = "cosine") -> torch.Tensor:
    """Noise variances beta_t [T] (float64). Cosine: Nichol & Dhariwal's alpha-bar curve."""
    if schedule == "linear":
        scale = 1000.0 / timesteps
        return torch.linspace(scale * 1e-4, scale * 0.02, timesteps, dtype=torch.float64)
    if schedule == "cosine":
        offset = 0.008
        steps = torch.arange(timesteps + 1, dtype=torch.float64) / timesteps
        alpha_bar = torch.cos((steps + offset) / (1 + offset) * math.pi / 2) ** 2
        betas = 1.0 - alpha_bar[1:] / alpha_bar[:-1]
        return betas.clamp(max=0.999)
    raise ValueError(f"unknown beta schedule {schedule!r} (use cosine or linear)")


def _evidence_kwargs(evidence: torch.Tensor | None) -> dict:
    """Keyword arguments passing evidence to the network only when there is some (networks
    without evidence inputs refuse it)."""
    return {} if evidence is None else {"evidence": evidence}


def _sky_probability(outputs: tuple[torch.Tensor, ...]) -> torch.Tensor | None:
    """The sky probability from a network's outputs (None without a sky head)."""
    return torch.sigmoid(outputs[2]) if len(outputs) > 2 else None


class GaussianDiffusion:
    """The noise schedule with q_sample, the training loss and DDIM sampling."""

    def __init__(self, config: NDNDiffusionConfig | None = None):
        self.config = config or NDNDiffusionConfig()
        self.config.validate()
        self.timesteps = self.config.timesteps
        self.betas = make_betas(self.timesteps, self.config.schedule)
        self.alphas_cumprod = torch.cumprod(1.0 - self.betas, dim=0)  # [T] float64, decreasing
        # the baseline: the same network fed zero states at t = 0 predicts the clean maps directly
        self.regression = self.config.prediction == "regression"

    def _alpha_bar(self, timesteps: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return self.alphas_cumprod.to(like.device)[timesteps].to(like.dtype).view(-1, *([1] * (like.dim() - 1)))

    def q_sample(self, x0: torch.Tensor, timesteps: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """x_t = sqrt(alpha_bar_t) x0 + sqrt(1 - alpha_bar_t) noise; ``x0`` [B, ...], ``timesteps`` [B]."""
        alpha_bar = self._alpha_bar(timesteps, x0)
        return alpha_bar.sqrt() * x0 + (1.0 - alpha_bar).sqrt() * noise

    def target(self, x0: torch.Tensor, timesteps: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """What the network learns to output: the noise, or v = sqrt(ab) noise - sqrt(1-ab) x0."""
        if self.config.prediction == "epsilon":
            return noise
        alpha_bar = self._alpha_bar(timesteps, x0)
        return alpha_bar.sqrt() * noise - (1.0 - alpha_bar).sqrt() * x0

    def split_prediction(self, x_t: torch.Tensor, timesteps: torch.Tensor,
                         output: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(x0, epsilon) estimated from the network output at x_t."""
        alpha_bar = self._alpha_bar(timesteps, x_t)
        if self.config.prediction == "epsilon":
            epsilon = output
            x0 = (x_t - (1.0 - alpha_bar).sqrt() * epsilon) / alpha_bar.sqrt()
        else:
            x0 = alpha_bar.sqrt() * x_t - (1.0 - alpha_bar).sqrt() * output
            epsilon = (1.0 - alpha_bar).sqrt() * x_t + alpha_bar.sqrt() * output
        return x0, epsilon

    def training_loss(self, model: torch.nn.Module, views: torch.Tensor, depth: torch.Tensor, normal: torch.Tensor,
                      generator: torch.Generator | None = None, normal_weight: float = 1.0,
                      timesteps: torch.Tensor | None = None, *, evidence: torch.Tensor | None = None,
                      sky: torch.Tensor | None = None, sky_weight: float = 0.1) -> tuple[torch.Tensor, dict[str, float]]:
        """Mean squared error of the predicted noise (or v) of both branches at random steps.

        ``views`` [B, 9, H, W], ``depth`` [B, 1, H, W] and ``normal`` [B, 3, H, W] are the clean
        targets in [-1, 1]; ``evidence`` [B, 4, H, W] goes to a network that reads it. With a sky
        head, ``sky`` [B, 1, H, W] (1 = no surface) is its target: binary cross-entropy times
        ``sky_weight`` joins the loss. Returns (loss, {"depth": ..., "normal": ...[, "sky": ...]}).
        """
        batch = views.shape[0]
        if self.regression:
            outputs = model(views, *self._regression_inputs(views), **_evidence_kwargs(evidence))
            depth_loss = F.mse_loss(outputs[0], depth)
            normal_loss = F.mse_loss(outputs[1], normal)
        else:
            if timesteps is None:
                timesteps = torch.randint(0, self.timesteps, (batch,), generator=generator).to(views.device)
            depth_noise = torch.randn(depth.shape, generator=generator).to(depth)
            normal_noise = torch.randn(normal.shape, generator=generator).to(normal)
            outputs = model(views, self.q_sample(depth, timesteps, depth_noise),
                            self.q_sample(normal, timesteps, normal_noise), timesteps, **_evidence_kwargs(evidence))
            depth_loss = F.mse_loss(outputs[0], self.target(depth, timesteps, depth_noise))
            normal_loss = F.mse_loss(outputs[1], self.target(normal, timesteps, normal_noise))
        loss = depth_loss + normal_weight * normal_loss
        parts = {"depth": float(depth_loss.detach()), "normal": float(normal_loss.detach())}
        if len(outputs) > 2 and sky is not None:
            sky_loss = F.binary_cross_entropy_with_logits(outputs[2], sky.to(outputs[2].dtype))
            loss = loss + sky_weight * sky_loss
            parts["sky"] = float(sky_loss.detach())
        return loss, parts

    def ddim_timesteps(self, steps: int | None = None) -> list[int]:
        """The DDIM schedule: ``steps`` evenly spaced steps from T-1 down to 0."""
        steps = steps or self.config.sample_steps
        values = torch.linspace(self.timesteps - 1, 0, steps).round().long().tolist()
        return sorted(set(values), reverse=True)

    @torch.no_grad()
    def sample(self, model: torch.nn.Module, views: torch.Tensor, steps: int | None = None,
               seed: int = 0, ensemble: int | None = None, *, evidence: torch.Tensor | None = None,
               return_sky: bool = False) -> tuple[torch.Tensor, ...]:
        """Deterministic DDIM (eta = 0): views [B, 9, H, W] -> (depth [B, 1, H, W], normal [B, 3, H, W]).

        The starting noise comes from a generator seeded with ``seed``, so the same weights,
        views and seed always give the same maps. Estimates of x0 are clipped to [-1, 1].
        With ``ensemble`` n > 1 (default: the config's ``sample_ensemble``) each view is
        denoised n times from different noise (one batch of B x n) and the n results are
        combined per pixel by the config's ``sample_reduce`` (median: the lower middle value
        for even n; mean). Normals are combined component-wise and not renormalised here.
        ``evidence`` [B, 4, H, W] is passed to a network that reads it. With ``return_sky`` a
        third map, the sky probability [B, 1, H, W] of the last network pass (mean over an
        ensemble), is returned; None from a network without a sky head.
        """
        batch, _, height, width = views.shape
        if self.regression:
            outputs = model(views, *self._regression_inputs(views), **_evidence_kwargs(evidence))
            result = (outputs[0].clamp(-1.0, 1.0), outputs[1])
            return (*result, _sky_probability(outputs)) if return_sky else result
        ensemble = int(ensemble or self.config.sample_ensemble)
        if ensemble > 1:
            views = views.repeat_interleave(ensemble, dim=0)  # copies of a view are neighbours in the batch
            evidence = evidence.repeat_interleave(ensemble, dim=0) if evidence is not None else None
        generator = torch.Generator().manual_seed(int(seed))
        depth = torch.randn((views.shape[0], 1, height, width), generator=generator).to(views)
        normal = torch.randn((views.shape[0], 3, height, width), generator=generator).to(views)
        schedule = self.ddim_timesteps(steps)
        outputs: tuple[torch.Tensor, ...] = ()
        for index, step in enumerate(schedule):
            timesteps = torch.full((views.shape[0],), step, dtype=torch.long, device=views.device)
            outputs = model(views, depth, normal, timesteps, **_evidence_kwargs(evidence))
            previous = schedule[index + 1] if index + 1 < len(schedule) else -1
            depth = self._ddim_step(depth, timesteps, outputs[0], previous)
            normal = self._ddim_step(normal, timesteps, outputs[1], previous)
        sky = _sky_probability(outputs)
        if ensemble > 1:
            depth, normal = (self._combine(x.view(batch, ensemble, *x.shape[1:])) for x in (depth, normal))
            sky = sky.view(batch, ensemble, *sky.shape[1:]).mean(dim=1) if sky is not None else None
        return (depth, normal, sky) if return_sky else (depth, normal)

    def _combine(self, samples: torch.Tensor) -> torch.Tensor:
        """[B, n, C, H, W] -> [B, C, H, W] by the configured reduction over the n samples."""
        if self.config.sample_reduce == "mean":
            return samples.mean(dim=1)
        return samples.median(dim=1).values

    def _ddim_step(self, x_t: torch.Tensor, timesteps: torch.Tensor, output: torch.Tensor, previous: int) -> torch.Tensor:
        x0, epsilon = self.split_prediction(x_t, timesteps, output)
        x0 = x0.clamp(-1.0, 1.0)
        if previous < 0:
            return x0
        alpha_previous = float(self.alphas_cumprod[previous])
        return math.sqrt(alpha_previous) * x0 + math.sqrt(1.0 - alpha_previous) * epsilon

    def _regression_inputs(self, views: torch.Tensor) -> tuple[torch.Tensor, ...]:
        batch, _, height, width = views.shape
        return (views.new_zeros((batch, 1, height, width)), views.new_zeros((batch, 3, height, width)),
                torch.zeros((batch,), dtype=torch.long, device=views.device))
