"""Add-on preferences: the Python that runs the trainer (and setting one up), CPU threads,
default output folder.

The add-on's preferences are keyed by its root package: ``esgs`` under the bpy module,
``bl_ext.<repository>.esgs`` as an installed Blender extension; it is derived from
``__package__`` so both work.

The trainer Python is, in this order: ``$ESGS_PYTHON``; the *Trainer Python* preference;
the environment *Set Up Trainer* made in the extension's user directory
(:mod:`.trainer_setup`); the checkout's ``.venv``; Blender's own Python (which has no torch:
the preferences then show a warning).
"""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path
from typing import Optional

import bpy

from ..core.errors import ESGSError
from ..core.apps.jobs import find_python
from . import trainer_setup

#: the add-on's root package (``__package__`` is ``<root>.esgs_addon``)
ADDON_ID = __package__.rsplit(".", 1)[0]

#: the set-up running in the background (:class:`.trainer_setup.SetupJob`) and the lines of
#: the last *Check*; module state, since neither belongs in a .blend file
SETUP: dict = {"job": None, "check": []}
_TORCH_FOUND: dict[tuple[str, float], bool] = {}
_LOG_LINES = 8

_VARIANTS = [
    ("AUTO", "Automatic", "CUDA when an NVIDIA GPU is found (nvidia-smi), else CPU"),
    ("CPU", "CPU", "PyTorch's CPU build (about 200 MB; trains on the processor)"),
    ("CUDA", "CUDA", "PyTorch's CUDA build for NVIDIA GPUs (several GB)"),
]


class ESGS_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    python_path: bpy.props.StringProperty(
        name="Trainer Python",
        description="Python interpreter with torch and the esgs engine installed ($ESGS_PYTHON, when set, "
                    "comes first; empty: the trainer made by Set Up Trainer, then a checkout's .venv, then "
                    "Blender's own Python, which has no torch)",
        subtype="FILE_PATH",
    )
    threads: bpy.props.IntProperty(
        name="CPU threads", description="Threads the trainer may use (0: the libraries' default)", default=0, min=0)
    output_dir: bpy.props.StringProperty(
        name="Runs folder", description="Where training runs are written when a run folder is not given "
                                        "(empty: 'esgs_runs' beside the .blend file or the scene folder)",
        subtype="DIR_PATH",
    )
    torch_variant: bpy.props.EnumProperty(
        name="Torch Build", description="Which PyTorch build Set Up Trainer installs", items=_VARIANTS,
        default="AUTO")
    wheel_dir: bpy.props.StringProperty(
        name="Wheel Folder", description="A folder of downloaded wheels to set up from without internet "
                                         "(pip --no-index --find-links); empty: download from the package index",
        subtype="DIR_PATH")
    index_url: bpy.props.StringProperty(
        name="Index URL", description="A package index (a mirror) to set up from instead of PyPI and PyTorch's "
                                      "index; empty: the default ones")

    def draw(self, context):
        draw_preferences(self, self.layout)


def get_preferences(context: Optional[bpy.types.Context] = None) -> Optional[ESGS_AP_preferences]:
    """The add-on's preferences, or None when it was registered without being enabled (bpy module)."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_ID)
    return addon.preferences if addon is not None else None


def environment_dir(create: bool = False) -> Path:
    """Where *Set Up Trainer* puts the trainer: ``trainer`` in the extension's user directory
    (a checkout loaded as plain ``esgs`` is no extension: a folder of Blender's user resources)."""
    try:
        user_dir = bpy.utils.extension_path_user(ADDON_ID, create=create)
    except ValueError:
        user_dir = bpy.utils.user_resource("EXTENSIONS", path=os.path.join(".user", "checkout", ADDON_ID),
                                           create=create)
    return Path(user_dir) / trainer_setup.ENVIRONMENT_NAME


def trainer_choice(context: Optional[bpy.types.Context] = None) -> tuple[str, str]:
    """``(python, where it comes from)``: ``$ESGS_PYTHON``, the preference, the set-up trainer,
    the checkout's ``.venv``, Blender's own Python, the first that is there.

    Raises:
        ConfigError: ``$ESGS_PYTHON`` or the preference names a file that does not exist.
    """
    if os.environ.get("ESGS_PYTHON"):
        return find_python(), "$ESGS_PYTHON"
    prefs = get_preferences(context)
    if prefs is not None and prefs.python_path:
        return find_python(bpy.path.abspath(prefs.python_path)), "the Trainer Python preference"
    managed = trainer_setup.environment_python(environment_dir())
    if managed is not None:
        return str(managed), "Set Up Trainer"
    python = find_python()
    # find_python's .venv is the one of the add-on's own folder (a checkout); Blender's Python may
    # well live in some other .venv (the bpy module installed in a virtual environment)
    from_checkout = Path(python).absolute().is_relative_to(trainer_setup.PACKAGE_ROOT / ".venv")
    return python, ("the checkout's .venv" if from_checkout else "Blender's own Python")


def trainer_python(context: Optional[bpy.types.Context] = None) -> str:
    """The interpreter for the trainer (the order: :func:`trainer_choice`)."""
    return trainer_choice(context)[0]


def can_import_torch(python: str) -> bool:
    """Whether ``python`` finds torch (asked once per interpreter file and change of it)."""
    if os.path.realpath(python) == os.path.realpath(sys.executable):
        return importlib.util.find_spec("torch") is not None
    try:
        key = (python, os.path.getmtime(python))
    except OSError:
        return False
    if key not in _TORCH_FOUND:
        try:
            done = subprocess.run([python, "-c", "import importlib.util, sys; "
                                                 "sys.exit(importlib.util.find_spec('torch') is None)"],
                                  capture_output=True, timeout=30, env=trainer_setup.setup_environment(),
                                  stdin=subprocess.DEVNULL)
            _TORCH_FOUND[key] = done.returncode == 0
        except (OSError, subprocess.TimeoutExpired):
            _TORCH_FOUND[key] = False
    return _TORCH_FOUND[key]


def forget_trainer_checks() -> None:
    """Ask again whether the trainer finds torch (after a set-up, a removal, a *Check*)."""
    _TORCH_FOUND.clear()


def setup_options(context: Optional[bpy.types.Context] = None) -> dict:
    """:func:`.trainer_setup.run_setup`'s options from the preferences: Blender's own Python
    creates the environment; the torch build (automatic: CUDA when an NVIDIA GPU is found),
    the wheel folder and the index URL."""
    prefs = get_preferences(context)
    variant = prefs.torch_variant if prefs is not None else "AUTO"
    variant = trainer_setup.detect_variant()[0] if variant == "AUTO" else variant.lower()
    wheel_dir = bpy.path.abspath(prefs.wheel_dir) if prefs is not None and prefs.wheel_dir else None
    index_url = prefs.index_url.strip() if prefs is not None and prefs.index_url.strip() else None
    return {"python": sys.executable, "variant": variant, "find_links": wheel_dir, "index_url": index_url}


def setup_job() -> Optional[trainer_setup.SetupJob]:
    return SETUP["job"]


def draw_preferences(prefs, layout) -> None:
    """The preferences' draw(); ``prefs`` may be a stand-in with the same attributes."""
    layout.prop(prefs, "python_path")
    try:
        python, source = trainer_choice()
    except ESGSError as error:
        layout.label(text=str(error), icon="ERROR")
    else:
        layout.label(text=f"Trainer runs with: {python} ({source})", icon="CONSOLE")
        if not can_import_torch(python):
            layout.label(text="This Python cannot import torch: training and priors will fail. "
                              "Use Set Up Trainer below, or choose a Trainer Python that has it", icon="ERROR")
    layout.prop(prefs, "threads")
    layout.prop(prefs, "output_dir")
    draw_setup(prefs, layout.box())


def draw_setup(prefs, box) -> None:
    box.label(text="Trainer environment", icon="PREFERENCES")
    target = environment_dir()
    job = setup_job()
    if job is not None and job.active:
        box.label(text=f"Setting up ({trainer_setup.format_elapsed(job.elapsed_s)}): {job.step}", icon="SORTTIME")
        box.operator("esgs.trainer_setup_cancel", icon="CANCEL")
    else:
        variant, reason = trainer_setup.detect_variant()
        row = box.row()
        row.prop(prefs, "torch_variant")
        row.label(text=f"Automatic: {variant.upper()} ({reason})")
        box.prop(prefs, "wheel_dir")
        box.prop(prefs, "index_url")
        row = box.row()
        row.operator("esgs.trainer_setup", icon="IMPORT")
        row.operator("esgs.trainer_check", icon="VIEWZOOM")
        row.operator("esgs.trainer_remove", icon="TRASH")
        present = trainer_setup.environment_python(target)
        box.label(text=f"{'Installed' if present else 'Not set up'}: {target}",
                  icon="CHECKMARK" if present else "INFO")
    if job is not None:
        if job.status == "failed":
            box.label(text="The set-up failed; nothing was kept", icon="ERROR")
        elif job.status == "cancelled":
            box.label(text="The set-up was cancelled; nothing was kept", icon="INFO")
        elif job.status == "finished":
            box.label(text=f"The trainer is ready (set up in {trainer_setup.format_elapsed(job.elapsed_s)})",
                      icon="CHECKMARK")
        log = box.column(align=True)
        for line in job.tail(_LOG_LINES):
            log.label(text=line[:160])
    for line in SETUP["check"]:
        box.label(text=line, icon="ERROR" if line.startswith("problem:") else "NONE")


def trainer_threads(context: Optional[bpy.types.Context] = None) -> int:
    prefs = get_preferences(context)
    return prefs.threads if prefs is not None else 0


def runs_folder(scene_dir: Path, context: Optional[bpy.types.Context] = None) -> Path:
    """Folder that receives new runs: the preference, else beside the .blend, else beside the scene."""
    prefs = get_preferences(context)
    if prefs is not None and prefs.output_dir:
        return Path(bpy.path.abspath(prefs.output_dir))
    if bpy.data.filepath:
        return Path(bpy.data.filepath).parent / "esgs_runs"
    return Path(scene_dir).parent / "esgs_runs"


CLASSES = (ESGS_AP_preferences,)
