"""Compute a scene's prior maps (auto, NDN or SfM) in the background: start and cancel (wrappers of
``esgs_addon/priors_job.py``)."""
from __future__ import annotations

import bpy

from ..core.errors import ESGSError
from ..core.formats.scene_dir import SceneDir
from ..esgs_addon import priors_job, training_job
from ._blocking import finish_headless_job


def _scene_dir(context):
    """The training's scene folder (:func:`training_job.find_scene_dir`); raises ESGSError."""
    return training_job.find_scene_dir(context.scene, context.scene.esgs.training.scene_dir, context.active_object)


class ESGS_OT_compute_priors(bpy.types.Operator):
    """Compute depth/normal prior maps (auto: the best of stereo labels, NDN and SfM per pixel; or NDN or
    SfM alone) for the training's scene folder in a separate process (blocking when Blender runs headless)"""

    bl_idname = "esgs.compute_priors"
    bl_label = "Compute Priors"

    @classmethod
    def poll(cls, context):
        try:
            folder = _scene_dir(context)
        except ESGSError:
            cls.poll_message_set("Render Dataset, Import COLMAP or choose the Training section's Scene folder first")
            return False
        if priors_job.running_job(folder) is not None:
            cls.poll_message_set("Priors are being computed for this scene")
            return False
        return True

    def execute(self, context):
        settings = context.scene.esgs.priors
        weights = bpy.path.abspath(settings.ndn_weights) if settings.method == "ndn" and settings.ndn_weights else None
        try:
            scene_dir = _scene_dir(context)
            job = priors_job.start_priors(scene_dir, settings.method, weights=weights)
        except ESGSError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        priors_job.copy_state(settings, job.state(), scene_dir=scene_dir, method=settings.method)
        target = SceneDir(scene_dir).prior(settings.method)
        if not bpy.app.background:
            priors_job.start_polling(context.scene.name, priors_job.job_key(scene_dir))
            self.report({"INFO"}, f"Computing {settings.method} priors into {target}")
            return {"FINISHED"}
        # headless: timers never fire, so follow the job here, printing progress
        method = settings.method
        return finish_headless_job(
            self, job, settings, wait=priors_job.wait_for_priors, copy_state=priors_job.copy_state, name="Priors",
            success_message=lambda state: f"Wrote {method} priors for {state.total} views to {target}")


class ESGS_OT_compute_priors_cancel(bpy.types.Operator):
    """Stop computing priors; the previous priors (or none) are kept"""

    bl_idname = "esgs.compute_priors_cancel"
    bl_label = "Cancel Priors"

    def execute(self, context):
        settings = context.scene.esgs.priors
        job = priors_job.running_job(settings.last_scene_dir) if settings.last_scene_dir else None
        if job is None:
            self.report({"WARNING"}, "No priors are being computed")
            return {"CANCELLED"}
        # the UI timer sees the job end; a headless caller has nothing to keep responsive
        state = job.cancel(timeout=30.0, wait=bool(bpy.app.background))
        priors_job.copy_state(settings, state)
        if bpy.app.background:
            job.cleanup()
        self.report({"INFO"}, "Stopping the priors job")
        return {"FINISHED"}


CLASSES = (ESGS_OT_compute_priors, ESGS_OT_compute_priors_cancel)
