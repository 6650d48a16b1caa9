"""Comparison methods of the paper that run inside our trainer: Mip-Splatting, DropoutGS, PGSR and Scaffold-GS.

Registered as ``"mip-splatting"``, ``"dropout-gs"``, ``"pgsr"`` and ``"scaffold-gs"`` in :mod:`esgs.core.methods`
(``esgs train --method mip-splatting``; the older ``--mip-splatting`` / ``--dropout-gs``
switches choose them too). See docs/baselines.md.
"""
from .config import DropoutGSConfig, MipSplattingConfig, PGSRConfig, ScaffoldGSConfig

__all__ = ["DropoutGSConfig", "MipSplattingConfig", "PGSRConfig", "ScaffoldGSConfig"]
