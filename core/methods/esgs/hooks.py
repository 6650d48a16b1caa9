"""The trainer hooks an ESGS configuration needs."""
from __future__ import annotations

from ...train.hooks import TrainHook
from .config import ESGSConfig


def esgs_hooks(config: ESGSConfig) -> list[TrainHook]:
    """The hooks a run with ``config`` needs (none when every part is off)."""
    from .gpdfn_hook import GPDFNHook
    from .prior_hook import PriorLossHook

    config.validate()
    hooks: list[TrainHook] = []
    if config.depth or config.normal or config.consistency or config.sky_loss_on or config.seeds_on:
        hooks.append(PriorLossHook(config))
    if config.gpdfn_on:
        hooks.append(GPDFNHook(config))
    return hooks
