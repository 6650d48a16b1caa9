"""Preferences > Set Up Trainer / Cancel / Check / Remove (wrappers of esgs_addon.trainer_setup).

*Set Up Trainer* runs in the background (a thread; a timer redraws the preferences with its
progress and log) and blocks when Blender runs headless, where timers never fire.
"""
from __future__ import annotations

from typing import Optional

import bpy

from ..core.errors import ESGSError
from ..esgs_addon import preferences, trainer_setup

_POLL_S = 0.5


def poll_setup() -> Optional[float]:
    """The timer callback: redraw the preferences while the set-up runs; at the end print how
    it went and forget the cached torch checks. Returns the next interval, None to stop."""
    job = preferences.setup_job()
    for window in getattr(bpy.context.window_manager, "windows", ()):
        for area in window.screen.areas:
            if area.type == "PREFERENCES":
                area.tag_redraw()
    if job is None or job.active:
        return _POLL_S if job is not None else None
    preferences.forget_trainer_checks()
    if job.status == "finished":
        preferences.SETUP["check"] = trainer_setup.describe(job.result)
        print("ESGS trainer set up:", *preferences.SETUP["check"], sep="\n  ", flush=True)
    else:
        print(f"ESGS trainer set-up {job.status}: {job.error}", flush=True)
    return None


class ESGS_OT_trainer_setup(bpy.types.Operator):
    """Create a Python environment for training in the extension's user folder: torch (CPU or CUDA build), the
    engine's requirements and the engine itself, checked with a test render (a few minutes; about 1-2 GB)"""

    bl_idname = "esgs.trainer_setup"
    bl_label = "Set Up Trainer"

    def execute(self, context):
        job = preferences.setup_job()
        if job is not None and job.active:
            self.report({"WARNING"}, "The trainer is already being set up")
            return {"CANCELLED"}
        try:
            options = preferences.setup_options(context)
            target = preferences.environment_dir(create=True)
        except ESGSError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        preferences.SETUP["check"] = [f"Torch build: {options['variant'].upper()}; into {target}"]
        if not bpy.app.background:
            preferences.SETUP["job"] = trainer_setup.SetupJob(target, **options).start()
            bpy.app.timers.register(poll_setup, first_interval=_POLL_S)
            self.report({"INFO"}, f"Setting up the trainer ({options['variant'].upper()} build) in {target}")
            return {"FINISHED"}
        # headless: timers never fire, so do it here, printing the steps' output
        try:
            found = trainer_setup.run_setup(target, on_line=lambda line: print(line, flush=True), **options)
        except ESGSError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        finally:
            preferences.forget_trainer_checks()
        preferences.SETUP["check"] = trainer_setup.describe(found)
        self.report({"INFO"}, "Trainer ready: " + "; ".join(preferences.SETUP["check"]))
        return {"FINISHED"}


class ESGS_OT_trainer_setup_cancel(bpy.types.Operator):
    """Stop setting up the trainer; what was installed so far is removed"""

    bl_idname = "esgs.trainer_setup_cancel"
    bl_label = "Cancel Set-Up"

    def execute(self, context):
        job = preferences.setup_job()
        if job is None or not job.active:
            self.report({"WARNING"}, "No trainer set-up is running")
            return {"CANCELLED"}
        job.cancel()
        return {"FINISHED"}


class ESGS_OT_trainer_check(bpy.types.Operator):
    """Show which Python runs the trainer, where it lives, its torch and numpy versions and whether it trains on
    the CPU or a GPU"""

    bl_idname = "esgs.trainer_check"
    bl_label = "Check"

    def execute(self, context):
        preferences.forget_trainer_checks()
        try:
            python, source = preferences.trainer_choice(context)
        except ESGSError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        found = trainer_setup.check_trainer(python)
        lines = [f"Trainer from {source}"] + trainer_setup.describe(found)
        preferences.SETUP["check"] = lines
        self.report({"ERROR" if found.get("error") else "INFO"}, "; ".join(lines))
        return {"CANCELLED" if found.get("error") else "FINISHED"}


class ESGS_OT_trainer_remove(bpy.types.Operator):
    """Delete the trainer environment that Set Up Trainer made (a Trainer Python chosen in the preferences is
    never touched)"""

    bl_idname = "esgs.trainer_remove"
    bl_label = "Remove"

    def invoke(self, context, event):
        return context.window_manager.invoke_confirm(self, event)

    def execute(self, context):
        job = preferences.setup_job()
        if job is not None and job.active:
            self.report({"WARNING"}, "Cancel the running set-up first")
            return {"CANCELLED"}
        target = preferences.environment_dir()
        removed = trainer_setup.remove_environment(target)
        preferences.forget_trainer_checks()
        preferences.SETUP["check"] = []
        self.report({"INFO"}, f"Removed the trainer: {target}" if removed else f"No trainer was set up in {target}")
        return {"FINISHED"}


CLASSES = (ESGS_OT_trainer_setup, ESGS_OT_trainer_setup_cancel, ESGS_OT_trainer_check, ESGS_OT_trainer_remove)


def unregister_hooks() -> None:
    if bpy.app.timers.is_registered(poll_setup):
        bpy.app.timers.unregister(poll_setup)
