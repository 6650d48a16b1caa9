"""The registry of training methods: one name, one settings dataclass, one way to build it.

``esgs train --method NAME``, ``TrainConfig.method``, the bench, the demo and the Blender
panel all look methods up here. Adding a method is one module (its settings dataclass and a
``build(settings, train_config) -> MethodParts`` function, importing torch lazily) plus one
:func:`register_method` call (see ``tests/core/methods/test_registry.py`` for a method that
only adds an opacity penalty, registered from a test without touching the trainer).
"""
from __future__ import annotations

from typing import Any

from ..errors import ConfigError
from ..train.method import PLAIN_3DGS, Method, MethodParts, RenderOptions
from .baselines.config import DropoutGSConfig, MipSplattingConfig, PGSRConfig, ScaffoldGSConfig
from .esgs.config import ESGSConfig

_METHODS: dict[str, Method] = {}


def register_method(method: Method, *, replace: bool = False) -> Method:
    """Make ``method`` known by its name; a second method of the same name needs ``replace``."""
    if method.name in _METHODS and not replace:
        raise ConfigError(f"a method named {method.name!r} is registered already",
                          hint="choose another name, or pass replace=True")
    _METHODS[method.name] = method
    return method


def unregister_method(name: str) -> None:
    """Forget a registered method (tests and plug-ins that register temporary methods)."""
    _METHODS.pop(name, None)


def get_method(name: str) -> Method:
    """The registered method called ``name``; ConfigError naming the known ones otherwise."""
    try:
        return _METHODS[name]
    except KeyError:
        raise ConfigError(f"unknown training method {name!r}",
                          hint=f"choose one of {', '.join(method_names())}") from None


def method_names() -> tuple[str, ...]:
    """The registered method names, in registration order (3dgs first)."""
    return tuple(_METHODS)


# --- the methods that ship ----------------------------------------------------------------
def _build_esgs(settings: ESGSConfig, config: Any) -> MethodParts:
    from .esgs.hooks import esgs_hooks

    return MethodParts(hooks=esgs_hooks(settings))


def _build_mip_splatting(settings: MipSplattingConfig, config: Any) -> MethodParts:
    from .baselines.mip_splatting import MipSplattingHook

    settings.validate()
    return MethodParts(hooks=[MipSplattingHook(settings)], render=_mip_render_options(settings))


def _mip_render_options(settings: MipSplattingConfig) -> RenderOptions:
    # the 2D half of Mip-Splatting: the rasterizer's screen-space filter
    return RenderOptions(antialiased=True, eps2d=settings.mip_filter_2d)


def _build_dropout_gs(settings: DropoutGSConfig, config: Any) -> MethodParts:
    from .baselines.dropout_gs import DropoutHook

    settings.validate()
    return MethodParts(hooks=[DropoutHook(settings)] if settings.dropout_rate > 0 else [])


def _build_pgsr(settings: PGSRConfig, config: Any) -> MethodParts:
    from .baselines.pgsr import PGSRHook

    settings.validate()
    return MethodParts(hooks=[PGSRHook(settings)])


def _build_scaffold_gs(settings: ScaffoldGSConfig, config: Any) -> MethodParts:
    from .baselines.scaffold_gs import scaffold_parts

    return scaffold_parts(settings, config)


register_method(PLAIN_3DGS)
register_method(Method(name="esgs", label="ESGS", settings_class=ESGSConfig, build=_build_esgs,
                       description="3DGS with depth/normal prior losses and GPDFN neighbour fusion (the paper's method)"))
register_method(Method(name="mip-splatting", label="Mip-Splatting", settings_class=MipSplattingConfig,
                       build=_build_mip_splatting, render_options=_mip_render_options,
                       description="3D smoothing filter from the training cameras plus a 2D anti-aliasing filter"))
register_method(Method(name="dropout-gs", label="DropoutGS", settings_class=DropoutGSConfig, build=_build_dropout_gs,
                       description="drops a random fraction of the Gaussians from every training render"))
register_method(Method(name="pgsr", label="PGSR", settings_class=PGSRConfig, build=_build_pgsr,
                       description="planar Gaussians: flattening, unbiased depth, single- and multi-view geometric "
                                   "consistency (Chen et al. 2024)"))
register_method(Method(name="scaffold-gs", label="Scaffold-GS", settings_class=ScaffoldGSConfig,
                       build=_build_scaffold_gs,
                       description="anchors on a voxel grid whose features decode view-dependent neural Gaussians "
                                   "through small MLPs, grown and pruned by gradient and opacity (Lu et al. 2024)"))
