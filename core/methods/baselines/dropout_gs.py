"""DropoutGS (Xu et al., CVPR 2025), its random dropout regularisation as a trainer hook.

Each training step renders a random sub-model: a fixed fraction of the Gaussians gets
opacity 0 (so they neither occlude nor colour any pixel, exactly as if removed) and the
photometric loss trains the kept ones to explain the image on their own. Evaluation and
export use the full model (the hook acts only in ``before_render``, which only training
calls). The edge-guided splitting of the paper is not implemented (docs/baselines.md).
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any, Optional

import torch

from ...train.gaussians import RenderParams
from ...train.hooks import RunView, StepContext, TrainHook
from .config import DropoutGSConfig

#: Mixed into the run seed so the dropout stream differs from torch's global one.
_SEED_SALT = 0x5D0F


def dropout_keep_mask(count: int, rate: float, *, seed: int, step: int,
                      device: torch.device | str = "cpu") -> torch.Tensor:
    """[count] bool, True = kept: exactly ``round(rate * count)`` Gaussians are dropped.

    The choice depends only on (seed, step), so a resumed run drops the same Gaussians as
    an uninterrupted one without saving any random state.
    """
    generator = torch.Generator(device="cpu")
    generator.manual_seed((int(seed) * 1_000_003 + int(step) * 7919 + _SEED_SALT) % (2 ** 63))
    dropped = int(round(rate * count))
    keep = torch.ones(count, dtype=torch.bool)
    if dropped > 0:
        keep[torch.randperm(count, generator=generator)[:dropped]] = False
    return keep.to(device)


def apply_dropout(params: Any, keep: torch.Tensor, *, compensate: bool = False, rate: float = 0.0) -> Any:
    """RenderParams with the opacities of dropped Gaussians set to 0 (differentiable for the kept).

    ``compensate`` divides the kept opacities by (1 - rate), clamped to 1 (DropGaussian).
    """
    opacities = params.opacities * keep.to(params.opacities.dtype)
    if compensate and rate > 0:
        opacities = (opacities / (1.0 - rate)).clamp(max=1.0)
    return replace(params, opacities=opacities)


class DropoutHook(TrainHook):
    """Drops ``config.dropout_rate`` of the Gaussians from every training render."""

    name = "baseline_dropout_gs"

    def __init__(self, config: DropoutGSConfig):
        self.config = config
        self.last_dropped = 0

    def before_render(self, run: RunView, context: StepContext, params: RenderParams) -> Optional[RenderParams]:
        count = params.opacities.shape[0]
        keep = dropout_keep_mask(count, self.config.dropout_rate, seed=run.seed, step=context.step,
                                 device=params.opacities.device)
        self.last_dropped = int(count - int(keep.sum()))
        context.extras["dropout_dropped"] = self.last_dropped
        return apply_dropout(params, keep, compensate=self.config.dropout_compensate, rate=self.config.dropout_rate)
