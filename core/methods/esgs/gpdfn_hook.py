"""Trainer hook that runs GPDFN before the render and trains it with the Gaussians.

By default GPDFN runs at every step (the paper's method). With ``every = k > 1`` it runs on
steps k, 2k, ... (and on the first step after any change of the Gaussian set); the steps
between add its last residuals, detached: neither the module nor the Gaussians receive
GPDFN gradients on those steps. docs/esgs.md gives the cost and the quality ablation.
"""
from __future__ import annotations

from typing import Any, Optional

import torch

from ...render.constants import NEAR_PLANE
from ...render.sh import SHCoefficients
from ...train.gaussians import GaussianModel, RenderParams
from ...train.hooks import RunView, StepContext, TrainHook
from .gpdfn import GPDFN
from .config import ESGSConfig


def gpdfn_residuals(module: GPDFN, gaussians: Any, params: Any,
                    rows: Optional[torch.Tensor] = None) -> dict[str, torch.Tensor]:
    """GPDFN's residuals for ``gaussians`` (raw parameters) given their activated ``params``.

    The rotations come from ``params.quats``, the renderer's unit quaternions
    (``GaussianModel.render_params``), so a step normalises them once, not twice. ``rows``:
    fuse only these Gaussians (:meth:`GPDFN.forward`), the others get zero residuals.
    """
    raw = gaussians.params
    return module(raw["means"], raw["log_scales"], params.quats, raw["opacity_logit"].reshape(-1),
                  raw["sh_dc"].reshape(-1, 3), unit_quats=True, rows=rows)


#: How far GPDFN's log-scale residual may grow a Gaussian for :func:`frustum_rows` to still
#: count it (e^1.4 ~ 4x its own scale); the rasterizer's radius rule is 3.33 sigma at most.
_RESIDUAL_GROWTH = 4.0
_SIGMA_RADIUS = 3.33


def frustum_rows(means: torch.Tensor, scales: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor,
                 width: int, height: int) -> torch.Tensor:
    """[M] sorted indices of the Gaussians one camera can draw, with a margin for GPDFN's residuals.

    A Gaussian counts when its centre is beyond the rasterizer's near plane and its projected
    centre lies within the image grown by a radius bound: 3.33 sigma of its largest scale
    grown :data:`_RESIDUAL_GROWTH` times, times the camera's focal length over the depth
    (off-screen Gaussians use a clamped Jacobian, which the growth factor also covers), plus a
    pixel for the 2D dilation. The Gaussians left out are drawn by no rasterizer rule unless a
    residual grows them more than that, so fusing only these leaves the step's render and its
    gradients as they are. means [N, 3] world; scales [N, 3] activated; viewmat [4, 4]; K [3, 3].
    """
    with torch.no_grad():
        rotation, translation = viewmat[:3, :3].to(means), viewmat[:3, 3].to(means)
        camera = means.detach() @ rotation.T + translation
        depth = camera[:, 2]
        in_front = depth > NEAR_PLANE
        safe = torch.where(in_front, depth, torch.ones_like(depth))
        fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        u = fx * camera[:, 0] / safe + cx
        v = fy * camera[:, 1] / safe + cy
        radius = _SIGMA_RADIUS * _RESIDUAL_GROWTH * scales.detach().amax(dim=-1) * max(fx, fy) / safe + 1.0
        outside_u = (u - u.clamp(0.0, float(width))).abs()
        outside_v = (v - v.clamp(0.0, float(height))).abs()
        keep = in_front & (outside_u <= radius) & (outside_v <= radius)
        return torch.nonzero(keep).reshape(-1)


def fused_render_params(module: GPDFN, gaussians: Any, params: Any) -> Any:
    """Apply GPDFN residuals to activated rendering parameters (a new RenderParams)."""
    return apply_residuals(gaussians, params, gpdfn_residuals(module, gaussians, params))


def apply_residuals(gaussians: Any, params: Any, residual: dict[str, torch.Tensor]) -> Any:
    """RenderParams with GPDFN's ``residual`` (sh_dc [N,3], opacity_logits [N], log_scales [N,3]) added."""
    from dataclasses import replace

    raw = gaussians.params
    scales = torch.exp(raw["log_scales"] + residual["log_scales"])
    opacities = torch.sigmoid(raw["opacity_logit"].reshape(-1) + residual["opacity_logits"])
    colors = params.colors
    if not isinstance(colors, SHCoefficients):  # one [N, K, 3] tensor: its two parts, as views
        colors = SHCoefficients(colors[:, :1], colors[:, 1:])
    # the residual goes to the degree-0 coefficients alone; the higher bands pass through uncopied
    colors = SHCoefficients(colors.dc + residual["sh_dc"].unsqueeze(1), colors.rest)
    return replace(params, scales=scales, opacities=opacities, colors=colors)


#: Mixed into the run seed for GPDFN's initial weights, so they differ from torch's global stream.
_SEED_SALT = 0x6DF2


class GPDFNHook(TrainHook):
    """Owns the GPDFN module: optimiser group, residuals before render, checkpoint state."""

    name = "esgs_gpdfn"

    def __init__(self, config: ESGSConfig):
        self.config = config
        self.module = GPDFN(config)
        self.every = config.gpdfn_every
        # detached residuals of the last GPDFN run (reused on the steps between runs)
        self._cached: Optional[dict[str, torch.Tensor]] = None

    def setup(self, run: RunView) -> None:
        # initial weights from the run's seed, not from whatever the global generator holds when
        # the hook is built (that made ESGS runs differ with what ran before in the process);
        # fork_rng leaves the run's own random stream untouched
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed((int(run.seed) * 1_000_003 + _SEED_SALT) % (2 ** 63))
            self.module = GPDFN(self.config)
        self.module.to(run.device)
        if self.module.enabled:
            run.add_parameter_group("gpdfn", list(self.module.parameters()), self.config.gpdfn_lr)

    def before_render(self, run: RunView, context: StepContext, params: RenderParams) -> Optional[RenderParams]:
        if not self.module.enabled:
            return params
        if self.every > 1 and self._cached is not None and context.step % self.every != 0:
            return apply_residuals(run.gaussians, params, self._cached)
        if self.every > 1:  # the cached residuals serve later views too: every Gaussian's
            residual = gpdfn_residuals(self.module, run.gaussians, params)
            self._cached = {name: value.detach() for name, value in residual.items()}
            return apply_residuals(run.gaussians, params, residual)
        # the step renders one view: fuse only the Gaussians it can draw (same render and gradients)
        view = context.view
        rows = frustum_rows(params.means, params.scales, view.viewmat, view.K, view.width, view.height)
        return apply_residuals(run.gaussians, params, gpdfn_residuals(self.module, run.gaussians, params, rows))

    def model_params(self, run: RunView, params: RenderParams) -> RenderParams:
        """The model with every Gaussian fused with its neighbours by the current weights."""
        if not self.module.enabled:
            return params
        return apply_residuals(run.gaussians, params, gpdfn_residuals(self.module, run.gaussians, params))

    def on_densify(self, run: RunView, report: Any) -> None:
        # the cached residuals belong to the old Gaussian set (order and count)
        self._cached = None
        if getattr(report, "reset_opacity", False) and self.module.enabled:
            # the reset must reach the opacity the renderer draws, not only the Gaussians' own:
            # GPDFN's learnt residual would push the reset Gaussians below the 1/255 cull
            self.module.reset_opacity_residual()

    def bake(self, gaussians: Any) -> None:
        """Fold the current residuals into the Gaussians' own parameters (for export/eval)."""
        if not self.module.enabled or len(gaussians) == 0:
            return
        raw = gaussians.params
        with torch.no_grad():
            residual = self.module(raw["means"], raw["log_scales"], raw["quats"], raw["opacity_logit"].reshape(-1),
                                   raw["sh_dc"].reshape(-1, 3))
            raw["log_scales"].add_(residual["log_scales"])
            raw["opacity_logit"].add_(residual["opacity_logits"].reshape(raw["opacity_logit"].shape))
            raw["sh_dc"].add_(residual["sh_dc"].reshape(raw["sh_dc"].shape))

    def export_model(self, run: RunView, gaussians: GaussianModel) -> GaussianModel:
        """A copy of the Gaussians with the residuals folded in (the raw model keeps training)."""
        if not self.module.enabled:
            return gaussians
        copy = type(gaussians).from_state_dict(gaussians.state_dict())
        copy.to(run.device)
        self.bake(copy)
        return copy

    def state_dict(self) -> dict:
        return {"module": self.module.state_dict(), "voxel_size": self.module.voxel_size}

    def load_state_dict(self, state: dict) -> None:
        if state.get("module"):
            self.module.load_state_dict(state["module"])
        self.module.voxel_size = float(state.get("voxel_size", self.module.voxel_size))

