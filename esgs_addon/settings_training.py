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
from pathlib import Path
from typing import Any, Optional

import bpy
from bpy.app.handlers import persistent

from ..core.errors import ConfigError, ESGSError
from ..core.methods import get_method, method_names
from ..core.formats.scene_dir import PriorSource
from ..core.train.config import TrainConfig
from ._registry import file_load_hooks
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

#: the panel's training steps: a run that ends in minutes on a CPU (about 0.15-0.5 s a step at
#: 320x180, README "Known limitations"), where TrainConfig's default is the paper's 30,000 steps
#: (hours on a CPU); the step schedules scale with it (docs/training.md)
DEFAULT_ITERATIONS = 2000

#: the method drop-down's help (TrainConfig's speaks of ``esgs train --list-methods``)
METHOD_DESCRIPTION = "How to train: plain 3DGS, ESGS (depth/normal priors and GPDFN) or another published method"

_TRAIN_EXTRA = {
    "iterations": {"min": 1, "soft_max": 100_000, "default": DEFAULT_ITERATIONS,
                   "description": "Training steps (the paper trains 30,000: hours on a CPU; the schedules scale "
                                  "with the number of steps)"},
    # the dataclass's help speaks of the command line's --resolution
    "width": {"name": "Image width", "min": 0, "soft_max": 4096, "subtype": "PIXEL",
              "description": "Width in pixels the images are trained at (0: their own size)"},
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


# --------------------------------------------------------------------------- prior source
# ``priors`` (ESGSConfig's field) stays the stored string: scripts and .blend files saved
# earlier set it, and "" means no priors, which an enum item cannot be. The panel shows
# ``prior_source``, a drop-down over it of what the chosen scene folder holds.

#: the ``prior_source`` item for "no priors" (``priors == ""``)
NO_PRIORS = "NONE"

#: the sources Compute Priors makes for any scene (auto, ndn, sfm)
COMPUTED_SOURCES = tuple(source.value for source in PriorSource.computed())

#: the prior source choosing ESGS starts with: the one ``esgs train --esgs``, the demo and
#: :func:`~esgs.core.methods.full_esgs` default to (a test checks they agree)
DEFAULT_PRIOR_SOURCE = PriorSource.AUTO.value

#: what the auto source is, in the panel's words
AUTO_HELP = "Auto: best of stereo labels, NDN and SfM per pixel, with a confidence map"

_SOURCE_HELP = {
    PriorSource.GT: "exact depth, normals and sky mask rendered with the synthetic scene",
    PriorSource.LABELS: "depth and normals rendered from a mesh (the Labels section)",
    PriorSource.NDN: "dense relative depth and normals from the NDN network",
    PriorSource.SFM: "sparse depth at the COLMAP points each view observes",
    PriorSource.AUTO: AUTO_HELP,
}

#: how the drop-down marks a source that is not in the scene folder yet: Compute Priors makes
#: it, and training makes auto itself before its first step
COMPUTE_FIRST = " (compute first)"
MADE_BEFORE_TRAINING = " (made before training)"


def training_scene_dir(group: Any, context: Any = None) -> Optional[Path]:
    """The scene folder Training would use now (:func:`.training_job.find_scene_dir`: the
    panel's folder, else the imported scene's), or None when there is none yet."""
    from .training_job import find_scene_dir

    context = context or bpy.context
    try:
        return find_scene_dir(group.id_data, group.scene_dir, getattr(context, "active_object", None))
    except ESGSError:
        return None


def prior_source_choices(group: Any, context: Any = None) -> list[tuple[str, str, str]]:
    """``(identifier, name, description)`` of the prior sources the panel offers: none, auto
    (the default, computed before training when the scene folder has none yet), each
    ``priors/<source>`` folder the scene folder holds, the sources Compute Priors makes (ndn,
    sfm) when not there yet, and the current choice even when its folder is gone."""
    from ..core.priors.io import available_prior_sources

    folder = training_scene_dir(group, context)
    present = available_prior_sources(folder) if folder is not None else []
    order = [source.value for source in PriorSource]
    # the default first, then the rest most faithful first
    present.sort(key=lambda name: (name != DEFAULT_PRIOR_SOURCE,
                                   order.index(name) if name in order else len(order), name))
    items = [(NO_PRIORS, "None", "No prior maps (the consistency loss and GPDFN need none)")]
    if DEFAULT_PRIOR_SOURCE not in present:
        items.append((DEFAULT_PRIOR_SOURCE, DEFAULT_PRIOR_SOURCE + MADE_BEFORE_TRAINING,
                      f"{AUTO_HELP}; not in the scene folder yet: Train computes it first (stereo labels take "
                      "minutes), or press Compute Priors"))
    for name in present:
        help_text = _SOURCE_HELP.get(PriorSource(name)) if name in order else None
        items.append((name, name, f"priors/{name} of the scene folder" + (f": {help_text}" if help_text else "")))
    for source in PriorSource.computed():
        if source.value not in present and source.value != DEFAULT_PRIOR_SOURCE:
            items.append((source.value, source.value + COMPUTE_FIRST,
                          f"{_SOURCE_HELP[source]}; not in the scene folder yet: choose it, then press Compute Priors"))
    if group.priors and group.priors not in {item[0] for item in items}:
        items.append((group.priors, f"{group.priors} (missing)", f"the scene folder has no priors/{group.priors}"))
    return items


def _numbered(items: list[tuple[str, str, str]]) -> list[tuple[str, str, str, int]]:
    # fixed numbers for the known sources, so the stored choice survives a changing list
    order = [source.value for source in PriorSource]
    return [(identifier, name, description,
             0 if identifier == NO_PRIORS else order.index(identifier) + 1 if identifier in order else 100 + index)
            for index, (identifier, name, description) in enumerate(items)]


def _prior_source_items(self, context):
    items = _numbered(prior_source_choices(self, context))
    _prior_source_items.cache = items  # Blender keeps references to the strings of dynamic items
    return items


def _get_prior_source(self) -> int:
    current = self.priors or NO_PRIORS
    return next((number for identifier, _, _, number in _numbered(prior_source_choices(self))
                 if identifier == current), 0)


def _set_prior_source(self, value: int) -> None:
    for identifier, name, _, number in _numbered(prior_source_choices(self)):
        if number == value:
            self.priors = "" if identifier == NO_PRIORS else identifier  # its update offers the full method
            if identifier in COMPUTED_SOURCES and name.endswith((COMPUTE_FIRST, MADE_BEFORE_TRAINING)):
                self.id_data.esgs.priors.method = identifier  # Compute Priors beside it makes what was chosen
            return


def _esgs_parts_on(group: Any) -> bool:
    return any(bool(getattr(group, name)) for name in ESGS_PARTS)


def apply_full_esgs(group: Any) -> None:
    """Set ``group``'s ESGS settings to :func:`~esgs.core.methods.full_esgs` of its prior source
    (looked up when called: the demo, the CLI and this panel call the one definition)."""
    from ..core import methods

    settings = methods.full_esgs(group.priors)
    for name, value in dataclasses.asdict(settings).items():
        if name != "priors" and hasattr(group, name) and getattr(group, name) != value:
            setattr(group, name, value)


def _filled_in(group: Any) -> bool:
    """Whether ``group``'s ESGS settings are the full method of some source (filled in by the
    panel, e.g. auto's when ESGS was chosen), not settings the user changed by hand."""
    from ..core import methods

    settings = method_settings(group, ESGS_METHOD)
    for source in PriorSource.standard_sources():
        with contextlib.suppress(ConfigError):
            if dataclasses.replace(settings, priors=source.value) == methods.full_esgs(source.value):
                return True
    return False


def complete_saved_full_esgs(group: Any) -> list[str]:
    """Give a full ESGS saved in an older .blend the options the full method gained since.

    A .blend stores only the options that were set in it, so an option added to ESGS later
    reads as its dataclass default in an older file: a full method the panel filled in before
    ``prior_points`` existed would train without seeding, and would no longer count as the full
    method (:func:`_filled_in`), so choosing a source again would not mend it either. When
    ``group`` trains ESGS with a prior source and every ESGS option the file stored equals
    today's :func:`~esgs.core.methods.full_esgs` of that source, the options it never stored get
    the full method's values. An option the user set by hand is stored, even when set back to
    its default, so it is never touched, nor is a group that differs from the full method in
    any stored option. Returns the names of the options filled in (empty: nothing changed).
    """
    from ..core import methods

    if chosen_method(group) != ESGS_METHOD or not group.priors:
        return []
    try:
        wanted = dataclasses.asdict(methods.full_esgs(group.priors))
    except ConfigError:
        return []
    held = dataclasses.asdict(method_settings(group, ESGS_METHOD))
    names = [name for name in wanted if name != "priors" and hasattr(group, name)]
    if any(held[name] != wanted[name] for name in names if group.is_property_set(name)):
        return []  # the user's own settings
    missing = [name for name in names if not group.is_property_set(name) and held[name] != wanted[name]]
    if missing:
        apply_full_esgs(group)
    return missing


@persistent
def on_file_loaded(*_args: Any) -> None:
    """``load_post`` handler: :func:`complete_saved_full_esgs` for every scene of the new file."""
    for scene in bpy.data.scenes:
        settings = getattr(scene, "esgs", None)
        if settings is None:
            continue
        added = complete_saved_full_esgs(settings.training)
        if added:
            print(f"ESGS: {scene.name}: the full ESGS saved in this file gets the options added to it since: "
                  f"{', '.join(f'{name} = {getattr(settings.training, name)}' for name in added)}", flush=True)


register_hooks, unregister_hooks = file_load_hooks(on_file_loaded)


def _offer_full_esgs(self, context) -> None:
    # choosing ESGS with a prior source and nothing switched on gives the full method, as
    # `esgs train --method esgs --priors SOURCE` does, and so does another source while the
    # settings are still a full method the panel filled in (auto's depth weight is not
    # ndn's); a source it cannot use is left to the trainer's error
    if self.method != ESGS_METHOD or not self.priors or (_esgs_parts_on(self) and not _filled_in(self)):
        return
    with contextlib.suppress(ConfigError):  # an unknown source: the parts stay off, training_config says why
        apply_full_esgs(self)


def _method_chosen(self, context) -> None:
    # ESGS chosen with no prior source and nothing switched on: the full method on the default
    # source (auto), as `esgs train --esgs` and the demo train it; a source or parts chosen
    # earlier are kept
    if self.method == ESGS_METHOD and not self.priors and not _esgs_parts_on(self):
        self.priors = DEFAULT_PRIOR_SOURCE  # its update switches the full method on
    else:
        _offer_full_esgs(self, context)


def _annotations() -> dict[str, Any]:
    annotations: dict[str, Any] = {
        "scene_dir": bpy.props.StringProperty(
            name="Scene folder", subtype="DIR_PATH",
            description="COLMAP scene folder to train on (empty: the scene imported with ESGS > Import COLMAP)"),
        "run_dir": bpy.props.StringProperty(
            name="Run folder", subtype="DIR_PATH",
            description="Folder the run is written to (empty: a new folder in the preferences' runs folder)"),
    }
    annotations["method"] = bpy.props.EnumProperty(
        name="Method", description=METHOD_DESCRIPTION,
        items=[(name, get_method(name).label, get_method(name).description) for name in method_names()],
        default=DEFAULT_METHOD, update=_method_chosen)
    annotations.update(property_annotations(TrainConfig, _TRAIN_EXTRA, names=TRAIN_FIELDS))
    for method, settings_class in method_settings_classes():
        extra = {}
        if method == ESGS_METHOD:
            extra = {"priors": {"update": _offer_full_esgs}}
        derived = property_annotations(settings_class, extra)
        clashes = set(derived) & set(annotations)
        if clashes:
            raise TypeError(f"settings of method {method!r} reuse the option names {sorted(clashes)}")
        annotations.update(derived)
    if "priors" in annotations:
        annotations["prior_source"] = bpy.props.EnumProperty(
            name="Prior source", items=_prior_source_items, get=_get_prior_source, set=_set_prior_source,
            description="Prior maps ESGS trains with (default auto: best of stereo labels, NDN and SfM per "
                        "pixel, made before training when missing): a priors/<source> folder of the scene folder, "
                        "or one Compute Priors makes (auto, ndn, sfm)")
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
    """The method ``group`` trains: its ``method``, except that a method never chosen (plain
    3DGS by default) with an ESGS part switched on or a prior source chosen trains ESGS.
    Before the method selector existed those settings alone chose ESGS, so scenes (and
    scripts) of that time train as they did; 3DGS chosen in the drop-down trains 3DGS, even
    after ESGS was chosen and filled in its source and parts."""
    if group.method == DEFAULT_METHOD and ESGS_METHOD in method_names() and not group.is_property_set("method"):
        esgs = method_settings(group, ESGS_METHOD)
        if esgs.priors or any(getattr(esgs, name) for name in ESGS_PARTS):
            return ESGS_METHOD
    return group.method


@settings_group("training")
class ESGS_PG_training(bpy.types.PropertyGroup):
    """Options of ``esgs.train`` (derived from TrainConfig and the methods' settings) and the
    job's last known state."""

    __annotations__ = _annotations()
