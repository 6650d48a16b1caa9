"""ESGS on top of the 3DGS trainer: geometry-prior losses and GPDFN, as trainer hooks.

Set ``TrainConfig.esgs`` (an :class:`ESGSConfig`) and the trainer adds the hooks from
:func:`esgs.core.method.hooks.esgs_hooks` itself; the CLI flags are ``--priors``,
``--depth``, ``--normal``, ``--consistency``, ``--gpdfn``, ``--fused-k`` and the weights.
"""
from .config import ESGSConfig

__all__ = ["ESGSConfig"]
