"""Training settings and the live state of the scene's training job: ``scene.esgs.training``.

The options are derived from the engine's dataclasses, so each one (name, default, help
text) exists in one place: ``method`` is a drop-down of the registered methods
(:func:`esgs.core.methods.method_names`), a few :class:`~esgs.core.train.config.TrainConfig`
fields (:data:`TRAIN_FIELDS`) are the run's, and every registered method's settings
dataclass (ESGSConfig, MipSplattingConfig, DropoutGSConfig ...) adds its fields under their
own names (they are flat ``esgs train`` flags, unique across methods).
:func:`~.training_job.training_config` reads them back into a TrainConfig.
"""
from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator
from typing import Any

import bpy

from ..core.errors import ConfigError
from ..core.methods import full_esgs, get_method, method_names
from ..core.formats.scene_dir import PriorSource
from ..core.train.config import TrainConfig
from .properties import property_annotations, property_values, settings_group

#: the TrainConfig fields a Blender user sets (the child fills in every other default)
TRAIN_FIELDS = ("iterations", "width", "test_every", "seed", "backend", "max_minutes", "max_gaussians")

#: the method a fresh scene trains: the first registered (plain 3DGS)
DEFAULT_METHOD = method_names()[0]

#: the ESGS method (its settings are drawn as parts and promoted from old .blend files)
ESGS_METHOD = "esgs"

#: the ESGS switches of the panel (ESGSConfig fields; each has a ``<part>_weight`` beside it
#: when ESGSConfig has one)
ESGS_PARTS = ("depth", "normal", "consistency", "gpdfn")

_TRAIN_EXTRA = {
    "iterations": {"min": 1, "soft_max": 100_000},
    "width": {"name": "Image width", "min": 0, "soft_max": 4096, "subtype": "PIXEL"},
    "test_every": {"min": 0},
    "seed": {"min": 0},
    "max_minutes": {"min": 0.0},
    "max_gaussians": {"min": 1},
}


def method_settings_classes() -> Iterator[tuple[str, type]]:
    """``(method name, settings dataclass)`` of every registered method that has settings."""
    for name in method_names():
        settings_class = get_method(name).settings_class
        if settings_class is not None:
            yield name, settings_class


def _prior_source_suggestions(self, context, edit_text: str):
    # a string with suggestions rather than an enum: an enum cannot hold "" (= no priors),
    # and .blend files saved before this kept the source as a string
    return [(source.value, f"priors/{source.value}") for source in PriorSource]


def _esgs_parts_on(group: Any) -> bool:
    return any(bool(getattr(group, name)) for name in ESGS_PARTS)


def apply_full_esgs(group: Any) -> None:
    """Set ``group``'s ESGS settings to :func:`~esgs.core.methods.full_esgs` of its prior source."""
    settings = full_esgs(group.priors)
    for name, value in dataclasses.asdict(settings).items():
        if name != "priors" and hasattr(group, name) and getattr(group, name) != value:
            setattr(group, name, value)


def _offer_full_esgs(self, context) -> None:
    # choosing ESGS with a prior source and nothing switched on gives the full method, as
    # `esgs train --method esgs --priors SOURCE` does; a source it cannot use is left to the
    # trainer's error
    if self.method != ESGS_METHOD or not self.priors or _esgs_parts_on(self):
        return
    with contextlib.suppress(ConfigError):  # an unknown source: the parts stay off, training_config says why
        apply_full_esgs(self)


def _annotations() -> dict[str, Any]:
    annotations: dict[str, Any] = {
        "scene_dir": bpy.props.StringProperty(
            name="Scene folder", subtype="DIR_PATH",
            description="COLMAP scene folder to train on (empty: the scene imported with ESGS > Import COLMAP)"),
        "run_dir": bpy.props.StringProperty(
            name="Run folder", subtype="DIR_PATH",
            description="Folder the run is written to (empty: a new folder in the preferences' runs folder)"),
    }
    method_field = next(fld for fld in dataclasses.fields(TrainConfig) if fld.name == "method")
    annotations["method"] = bpy.props.EnumProperty(
        name="Method", description=method_field.metadata["help"],
        items=[(name, get_method(name).label, get_method(name).description) for name in method_names()],
        default=DEFAULT_METHOD, update=_offer_full_esgs)
    annotations.update(property_annotations(TrainConfig, _TRAIN_EXTRA, names=TRAIN_FIELDS))
    for method, settings_class in method_settings_classes():
        extra = {}
        if method == ESGS_METHOD:
            extra = {"priors": {"search": _prior_source_suggestions, "search_options": {"SUGGESTION"},
                                "update": _offer_full_esgs}}
        derived = property_annotations(settings_class, extra)
        clashes = set(derived) & set(annotations)
        if clashes:
            raise TypeError(f"settings of method {method!r} reuse the option names {sorted(clashes)}")
        annotations.update(derived)
    annotations["import_result"] = bpy.props.BoolProperty(
        name="Import result", description="Import the trained Gaussians when training finishes", default=True)

    # live state, written by the job poller (also saved: the last run stays visible)
    annotations.update(
        status=bpy.props.StringProperty(name="Status", default=""),
        stage=bpy.props.StringProperty(name="Stage", default=""),
        step=bpy.props.IntProperty(name="Step", default=0),
        total=bpy.props.IntProperty(name="Total", default=0),
        progress=bpy.props.FloatProperty(name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR"),
        loss=bpy.props.FloatProperty(name="Loss", default=-1.0),
        psnr=bpy.props.FloatProperty(name="PSNR", default=-1.0),
        n_gaussians=bpy.props.IntProperty(name="Gaussians", default=-1),
        eta_s=bpy.props.FloatProperty(name="ETA", default=-1.0),
        error=bpy.props.StringProperty(name="Error", default=""),
        last_run_dir=bpy.props.StringProperty(name="Last run", subtype="DIR_PATH", default=""),
        last_scene_dir=bpy.props.StringProperty(name="Last scene", subtype="DIR_PATH", default=""),
    )
    return annotations


def method_settings(group: Any, method: str) -> Any:
    """The settings dataclass of ``method`` held by ``group`` (None for a method without settings)."""
    settings_class = get_method(method).settings_class
    return None if settings_class is None else settings_class(**property_values(group, settings_class))


def chosen_method(group: Any) -> str:
    """The method ``group`` trains: its ``method``, except that plain 3DGS with an ESGS part
    switched on or a prior source chosen trains ESGS. Before the method selector existed
    those settings alone chose ESGS, so scenes (and scripts) of that time train as they did."""
    if group.method == DEFAULT_METHOD and ESGS_METHOD in method_names():
        esgs = method_settings(group, ESGS_METHOD)
        if esgs.priors or any(getattr(esgs, name) for name in ESGS_PARTS):
            return ESGS_METHOD
    return group.method


@settings_group("training")
class ESGS_PG_training(bpy.types.PropertyGroup):
    """Options of ``esgs.train`` (derived from TrainConfig and the methods' settings) and the
    job's last known state."""

    __annotations__ = _annotations()
