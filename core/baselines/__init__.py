"""Comparison methods of the paper, as trainer hooks: Mip-Splatting and DropoutGS.

Set ``TrainConfig.baselines`` (a :class:`BaselinesConfig`) and the trainer adds the hooks
from :func:`baseline_hooks` itself; the CLI flags are ``--mip-splatting`` and
``--dropout-gs [--dropout-rate R]``. See docs/baselines.md.
"""
from .config import BaselinesConfig

__all__ = ["BaselinesConfig", "baseline_hooks"]


def baseline_hooks(config: BaselinesConfig) -> list:
    """The hooks a run with ``config`` needs (none when every baseline is off)."""
    from .dropout_gs import DropoutHook
    from .mip_splatting import MipSplattingHook

    config.validate()
    hooks: list = []
    if config.mip_splatting:
        hooks.append(MipSplattingHook(config))
    if config.dropout_gs and config.dropout_rate > 0:
        hooks.append(DropoutHook(config))
    return hooks
