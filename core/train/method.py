"""What a training method is, as the trainer sees it.

The trainer knows no method by name. A method (3DGS, ESGS, Mip-Splatting, ...) is a
:class:`Method`: a name, the dataclass of its settings, and a function that turns those
settings into :class:`MethodParts` (the hooks it installs, the densification strategy it
uses, how it renders). The registry of the methods that ship lives above the trainer, in
:mod:`esgs.core.methods`; a new method is one module plus one registration there.

Only :data:`PLAIN_3DGS` is defined here: the trainer's own behaviour with nothing added.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Optional

if TYPE_CHECKING:
    from .config import TrainConfig
    from .hooks import TrainHook
    from .strategy import Strategy


@dataclass(frozen=True)
class RenderOptions:
    """How a method renders, in training and evaluation alike.

    ``antialiased``: the rasterizer's 2D screen-space filter with opacity compensation
    (Mip-Splatting); ``eps2d``: its variance in pixels^2.
    """

    antialiased: bool = False
    eps2d: float = 0.3


@dataclass
class MethodParts:
    """What a method installs into one run.

    ``hooks``: called in this order, before any hook the caller adds; ``strategy``: the
    densification strategy (None = the trainer's :class:`~.strategy.DefaultStrategy` built
    from the run's TrainConfig); ``render``: :class:`RenderOptions` of every render.
    """

    hooks: list["TrainHook"] = field(default_factory=list)
    strategy: Optional["Strategy"] = None
    render: RenderOptions = field(default_factory=RenderOptions)


@dataclass(frozen=True)
class Method:
    """A training method: ``name`` (as in ``TrainConfig.method`` and ``esgs train --method``),
    ``settings_class`` (its settings dataclass, stored as ``TrainConfig.method_config``;
    None = no settings) and ``build(settings, train_config) -> MethodParts``.

    ``render_options(settings)`` gives the method's :class:`RenderOptions` without building
    its hooks (evaluating or re-rendering a finished run needs only those).
    """

    name: str
    label: str
    settings_class: Optional[type] = None
    build: Callable[[Any, "TrainConfig"], MethodParts] = field(default=lambda settings, config: MethodParts())
    render_options: Callable[[Any], RenderOptions] = field(default=lambda settings: RenderOptions())
    description: str = ""

    def default_settings(self) -> Any:
        """A new settings object with the method's defaults (None when it has no settings)."""
        return self.settings_class() if self.settings_class is not None else None

    def settings_of(self, config: "TrainConfig") -> Any:
        """``config.method_config`` as this method's settings dataclass.

        A dict (a config read from JSON) becomes the dataclass, with unknown keys rejected;
        None becomes the defaults. Raises ConfigError for settings of another type.
        """
        from ..config import config_from_dict
        from ..errors import ConfigError

        value = config.method_config
        if self.settings_class is None:
            if value not in (None, {}):
                raise ConfigError(f"method {self.name!r} has no settings, got {value!r}",
                                  hint="leave method_config empty for this method")
            return None
        if value is None:
            return self.settings_class()
        if isinstance(value, dict):
            return config_from_dict(self.settings_class, value)
        if not isinstance(value, self.settings_class):
            raise ConfigError(f"method {self.name!r} takes {self.settings_class.__name__} settings, "
                              f"got {type(value).__name__}")
        return value


#: The trainer with nothing added: 3D Gaussian Splatting (Kerbl et al. 2023).
PLAIN_3DGS = Method(name="3dgs", label="3DGS", description="3D Gaussian Splatting, the trainer's own loop")
