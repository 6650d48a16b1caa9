"""ESGS (the paper's method) on top of the 3DGS trainer: geometry-prior losses and GPDFN.

:class:`ESGSConfig` holds its settings; :func:`esgs_hooks` gives the trainer hooks a
configuration needs (:class:`~.prior_hook.PriorLossHook`, :class:`~.gpdfn_hook.GPDFNHook`).
The method is registered as ``"esgs"`` in :mod:`esgs.core.methods`, where the full method
(:func:`esgs.core.methods.full_esgs`) is defined once.
"""
from .config import ESGSConfig
from .gpdfn_settings import GPDFNConfig

__all__ = ["ESGSConfig", "GPDFNConfig"]
