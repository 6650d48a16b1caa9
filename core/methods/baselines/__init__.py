"""Comparison methods of the paper that run inside our trainer: Mip-Splatting, DropoutGS and PGSR.

Registered as ``"mip-splatting"``, ``"dropout-gs"`` and ``"pgsr"`` in :mod:`esgs.core.methods`
(``esgs train --method mip-splatting``; the older ``--mip-splatting`` / ``--dropout-gs``
switches choose them too). See docs/baselines.md.
"""
from .config import DropoutGSConfig, MipSplattingConfig, PGSRConfig

__all__ = ["DropoutGSConfig", "MipSplattingConfig", "PGSRConfig"]
