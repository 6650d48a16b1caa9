"""Train the scene's Gaussians in the background: start, cancel, resume (wrappers of training_job)."""
from __future__ import annotations

import bpy

from ..core.apps import jobs
from ..core.errors import ESGSError
from ..esgs_addon import training_job
from ._blocking import finish_headless_job

def _run(operator, context, resume: bool) -> set[str]:
    settings = context.scene.esgs.training
    try:
        if resume:
            if not settings.last_run_dir or not settings.last_scene_dir:
                raise ESGSError("there is no earlier run to resume", hint="start a training first")
            scene_dir, run_dir = settings.last_scene_dir, settings.last_run_dir
        else:
            scene_dir = training_job.find_scene_dir(context.scene, settings.scene_dir, context.active_object)
            run_dir = bpy.path.abspath(settings.run_dir) if settings.run_dir else None
        # a resumed run keeps the settings saved in its config.json: pass none that could override them
        config = None if resume else training_job.training_config(settings)
        first = None if resume else training_job.priors_made_first(scene_dir, config)
        job = training_job.start_training(scene_dir, run_dir, settings.iterations, config=config, resume=resume)
    except ESGSError as error:
        operator.report({"ERROR"}, str(error))
        return {"CANCELLED"}
    # missing auto priors pass the pre-check: the run makes them before its first step
    making = f"; it computes the {first} priors first (stereo labels, NDN and SfM: minutes)" if first else ""
    settings.last_scene_dir = str(job.scene_dir)
    settings.last_run_dir = str(job.run_dir)
    training_job.copy_state(settings, job.state())
    key = training_job.job_key(job.scene_dir)
    if not bpy.app.background:
        training_job.start_polling(context.scene.name, key, import_result=settings.import_result)
        operator.report({"INFO"}, f"Training started: {job.run_dir}{making}")
        return {"FINISHED"}
    # headless: timers never fire, so follow the job here, printing progress
    if making:
        operator.report({"INFO"}, f"Training {job.run_dir}{making}")

    def import_result(state) -> None:
        obj = training_job.import_run_result(job.run_dir, scene=context.scene, scene_dir=job.scene_dir)
        context.view_layer.objects.active = obj

    return finish_headless_job(
        operator, job, settings, wait=training_job.wait_for_training, copy_state=training_job.copy_state,
        name="Training", success_message=lambda state: finished_message(job.run_dir),
        after_success=import_result if settings.import_result else None,
        after_success_failure="Training finished but importing failed")


def finished_message(run_dir) -> str:
    """``Training finished: RUN`` and the run's figures, each under its name (held-out or training)."""
    results = training_job.run_results(run_dir)
    figures = training_job.format_results(results) if results else []
    return "; ".join([f"Training finished: {run_dir}"] + figures)


class ESGS_OT_train(bpy.types.Operator):
    """Train Gaussians on the scene folder in a separate process (blocking when Blender runs headless)"""

    bl_idname = "esgs.train"
    bl_label = "Train"

    def execute(self, context):
        return _run(self, context, resume=False)


class ESGS_OT_train_resume(bpy.types.Operator):
    """Continue the last training run from its latest checkpoint"""

    bl_idname = "esgs.train_resume"
    bl_label = "Resume Training"

    def execute(self, context):
        return _run(self, context, resume=True)


class ESGS_OT_train_cancel(bpy.types.Operator):
    """Stop the running training; it saves a checkpoint first, so it can be resumed"""

    bl_idname = "esgs.train_cancel"
    bl_label = "Cancel Training"

    def execute(self, context):
        settings = context.scene.esgs.training
        job = jobs.get_job(training_job.job_key(settings.last_scene_dir)) if settings.last_scene_dir else None
        if job is None or not job.running:
            self.report({"WARNING"}, "No training is running")
            return {"CANCELLED"}
        # the UI timer sees the job end; a headless caller has nothing to keep responsive
        state = job.cancel(wait=bool(bpy.app.background))
        training_job.copy_state(settings, state)
        self.report({"INFO"}, "Stopping training (saving a checkpoint)")
        return {"FINISHED"}


CLASSES = (ESGS_OT_train, ESGS_OT_train_resume, ESGS_OT_train_cancel)
