"""Comparison methods of the paper that run inside our trainer: Mip-Splatting and DropoutGS.

Registered as ``"mip-splatting"`` and ``"dropout-gs"`` in :mod:`esgs.core.methods`
(``esgs train --method mip-splatting``; the older ``--mip-splatting`` / ``--dropout-gs``
switches choose them too). See docs/baselines.md.
"""
from .config import DropoutGSConfig, MipSplattingConfig

__all__ = ["DropoutGSConfig", "MipSplattingConfig"]
