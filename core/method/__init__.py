"""ESGS on top of the 3DGS trainer: geometry-prior losses and GPDFN, as trainer hooks.

``esgs_hooks(ESGSConfig(...))`` returns the hooks to pass to
:func:`esgs.core.train.train`.
"""
from __future__ import annotations

from ..train.hooks import TrainHook
from .config import ESGSConfig
from .gpdfn_hook import GPDFNHook, fused_render_params
from .prior_hook import PriorLossHook


def esgs_hooks(config: ESGSConfig) -> list[TrainHook]:
    """The hooks a run with ``config`` needs (none for the plain baseline)."""
    config.validate()
    hooks: list[TrainHook] = []
    if config.depth or config.normal or config.consistency:
        hooks.append(PriorLossHook(config))
    if config.gpdfn and config.fused_k > 1:
        hooks.append(GPDFNHook(config))
    return hooks


__all__ = ["ESGSConfig", "GPDFNHook", "PriorLossHook", "esgs_hooks", "fused_render_params"]
