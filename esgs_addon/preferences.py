"""Add-on preferences: the Python that runs the trainer, CPU threads, default output folder.

The add-on's preferences are keyed by its root package: ``esgs`` under the bpy module,
``bl_ext.<repository>.esgs`` as an installed Blender extension; it is derived from
``__package__`` so both work.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import bpy

from ..core.errors import ESGSError
from ..core.apps.jobs import find_python

#: the add-on's root package (``__package__`` is ``<root>.esgs_addon``)
ADDON_ID = __package__.rsplit(".", 1)[0]


class ESGS_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    python_path: bpy.props.StringProperty(
        name="Trainer Python",
        description="Python interpreter with torch and the esgs engine installed (empty: $ESGS_PYTHON, then "
                    "the .venv in the extension's folder, then Blender's own Python, which has no torch)",
        subtype="FILE_PATH",
    )
    threads: bpy.props.IntProperty(
        name="CPU threads", description="Threads the trainer may use (0: the libraries' default)", default=0, min=0)
    output_dir: bpy.props.StringProperty(
        name="Runs folder", description="Where training runs are written when a run folder is not given "
                                        "(empty: 'esgs_runs' beside the .blend file or the scene folder)",
        subtype="DIR_PATH",
    )

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "python_path")
        try:
            layout.label(text=f"Trainer runs with: {find_python(bpy.path.abspath(self.python_path) or None)}",
                         icon="CONSOLE")
        except ESGSError as error:
            layout.label(text=str(error), icon="ERROR")
        layout.prop(self, "threads")
        layout.prop(self, "output_dir")


def get_preferences(context: Optional[bpy.types.Context] = None) -> Optional[ESGS_AP_preferences]:
    """The add-on's preferences, or None when it was registered without being enabled (bpy module)."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_ID)
    return addon.preferences if addon is not None else None


def trainer_python(context: Optional[bpy.types.Context] = None) -> str:
    """The interpreter for the trainer (see :func:`esgs.core.apps.jobs.find_python`)."""
    prefs = get_preferences(context)
    preferred = bpy.path.abspath(prefs.python_path) if prefs is not None and prefs.python_path else None
    return find_python(preferred)


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
