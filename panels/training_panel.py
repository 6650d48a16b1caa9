"""Sidebar > ESGS > Training: options, progress of the background job, cancel and resume."""
from __future__ import annotations

import bpy

from ..core.apps.jobs import format_duration
from ..core.formats.scene_dir import SceneDir
from ..core.methods import get_method
from ..esgs_addon import interrupted_jobs, settings_training, training_estimate, training_job
from ..esgs_addon.properties import property_values
from ._section import ESGSSection

ORDER = 110  # after the import panel

#: shown while there is no scene folder to train on
NO_SCENE = "Render Dataset, Import COLMAP or choose a Scene folder"


class ESGS_PT_training(ESGSSection, bpy.types.Panel):
    """Train Gaussians on the imported scene in a separate process."""

    bl_label = "Training"
    bl_idname = "ESGS_PT_training"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        settings = context.scene.esgs.training
        running = settings.status in ("pending", "running")

        column = layout.column()
        column.enabled = not running
        column.prop(settings, "scene_dir")
        scene_dir = settings_training.training_scene_dir(settings, context)
        if scene_dir is None:
            column.label(text=NO_SCENE, icon="INFO")
        elif not settings.scene_dir:
            column.label(text=f"Scene: {scene_dir.name}", icon="FILE_FOLDER")
        column.prop(settings, "run_dir")
        column.prop(settings, "method")
        column.prop(settings, "iterations")
        if not running:  # a running job shows its ETA instead
            for index, line in enumerate(training_estimate.estimate_lines(settings, context, scene_dir)):
                column.label(text=line, icon="TIME" if index == 0 else "BLANK1")
        column.prop(settings, "width")
        method = settings_training.chosen_method(settings)
        if method == settings_training.ESGS_METHOD:
            _draw_esgs(column.box(), settings, context.scene.esgs.priors, scene_dir)
        else:
            _draw_method_settings(column, settings, method)
            # prior maps also give plain runs their sky masks (TrainConfig.mask_source), so
            # computing them stays at hand whatever the method
            box = column.box()
            box.label(text="Priors")
            _draw_priors(box, context.scene.esgs.priors)
        run = column.box()
        run.label(text="Run")
        for name in settings_training.TRAIN_FIELDS:
            if name not in ("iterations", "width"):
                run.prop(settings, name)
        column.prop(settings, "import_result")

        if running:
            text = f"{settings.step:,} / {settings.total:,}"
            if settings.stage and settings.stage != "train":
                text = f"{settings.stage}: {text}"  # evaluation after training has its own count
            layout.progress(factor=settings.progress, type="BAR", text=text)
            if settings.step == 0 and _making_priors(settings):
                layout.label(text=f"Computing {settings.priors} priors before the first step", icon="INFO")
            grid = layout.grid_flow(columns=2, even_columns=True)
            if settings.loss >= 0:
                grid.label(text=f"Loss {settings.loss:.4g}")
            if settings.psnr >= 0:
                # evaluation after training measures held-out views; training its own views
                grid.label(text=f"{_sentence(training_job.psnr_label(settings.stage))} {settings.psnr:.2f} dB")
            if settings.n_gaussians >= 0:
                grid.label(text=f"{settings.n_gaussians:,} Gaussians")
            if settings.eta_s >= 0:
                grid.label(text=f"ETA {format_duration(settings.eta_s)}")
            layout.operator("esgs.train_cancel", icon="CANCEL")
            return

        row = layout.row(align=True)
        row.operator("esgs.train", icon="PLAY")
        if settings.last_run_dir and settings.status in ("cancelled", "failed", interrupted_jobs.INTERRUPTED):
            row.operator("esgs.train_resume", icon="FILE_REFRESH")
        if settings.status:
            layout.label(text=f"Last run: {settings.status}", icon="CHECKMARK" if settings.status == "finished" else "INFO")
        if settings.status == "finished" and settings.last_run_dir:
            results = training_job.run_results(settings.last_run_dir)
            if results is not None:
                draw_run_results(layout.box(), results)
        if settings.error:
            box = layout.box()
            for index, line in enumerate(_wrap(settings.error, 48)):
                box.label(text=line, icon="ERROR" if index == 0 else "NONE")


def _making_priors(settings) -> bool:
    """Whether the running job is computing the auto priors before training (a new ESGS run on
    auto priors whose folder is not there yet: Train let it start, the run makes them)."""
    if settings.priors != settings_training.DEFAULT_PRIOR_SOURCE or not settings.last_scene_dir:
        return False
    if settings_training.chosen_method(settings) != settings_training.ESGS_METHOD:
        return False
    return not SceneDir(settings.last_scene_dir).has_prior_maps(settings.priors, "depth")


def draw_run_results(layout: bpy.types.UILayout, results: dict) -> None:
    """A finished run's figures (:func:`~..esgs_addon.training_job.run_results`), each under
    its name: held-out PSNR / SSIM / LPIPS, the last training PSNR, distances to the mesh."""
    held_out = results.get("held_out") or {}
    if held_out.get("psnr") is not None:
        views = held_out.get("views_count")
        if held_out.get("split", "test") == "test":
            title = f"Held-out views ({views} not trained on)" if views else "Held-out views"
        else:
            title = "Training views (the scene has no held-out split)"
        layout.label(text=title, icon="IMAGE_REFERENCE")
        grid = layout.grid_flow(columns=3, even_columns=True)
        prefix = "Held-out " if held_out.get("split", "test") == "test" else ""
        grid.label(text=f"{prefix}PSNR {held_out['psnr']:.2f} dB")
        if held_out.get("ssim") is not None:
            grid.label(text=f"{prefix}SSIM {held_out['ssim']:.3f}")
        if held_out.get("lpips") is not None:
            grid.label(text=f"{prefix}LPIPS {held_out['lpips']:.3f}")
        elif held_out.get("lpips_unavailable"):
            grid.label(text="LPIPS n/a")
    else:
        layout.label(text="No held-out figures (evaluation off or not finished)", icon="INFO")
    if results.get("training_psnr") is not None:
        layout.label(text=f"{_sentence(training_job.TRAINING_PSNR_LABEL)}: {results['training_psnr']:.2f} dB")
    comparison = results.get("comparison") or {}
    stats = comparison.get("gaussians_to_mesh_filtered") or comparison.get("gaussians_to_mesh") or {}
    if stats.get("mean") is not None:
        layout.label(text="Distances to the ground-truth mesh", icon="DRIVER_DISTANCE")
        grid = layout.grid_flow(columns=2, even_columns=True)
        grid.label(text=f"Mean {stats['mean']:.3g} m")
        if stats.get("median") is not None:
            grid.label(text=f"Median {stats['median']:.3g} m")
        if comparison.get("fscore") is not None:
            grid.label(text=f"F-score {comparison['fscore']:.3f}")
        if comparison.get("threshold_m") is not None:
            grid.label(text=f"at {comparison['threshold_m']:.3g} m")
    elif results.get("has_ground_truth_mesh"):
        layout.label(text="Distances: import the result, then Gaussians > Compare to Mesh", icon="INFO")


def _draw_esgs(layout: bpy.types.UILayout, settings, priors, scene_dir) -> None:
    """ESGS's parts: the prior source (and its computation), each part's switch and weight."""
    layout.label(text="ESGS")
    layout.prop(settings, "prior_source")
    if not settings.priors:
        layout.label(text="Choose a prior source for the full method", icon="INFO")
    elif scene_dir is not None and not SceneDir(scene_dir).has_prior_maps(settings.priors, "depth") \
            and not SceneDir(scene_dir).has_prior_maps(settings.priors, "normal"):
        icon = "ERROR"
        if settings.priors == settings_training.DEFAULT_PRIOR_SOURCE:
            # training makes them itself (or Compute Priors beforehand): nothing to fix
            text, icon = f"No {settings.priors} priors yet: Train computes them first", "INFO"
        elif settings.priors in settings_training.COMPUTED_SOURCES:
            text = f"No {settings.priors} priors yet: press Compute Priors ({settings.priors})"
        else:
            text = f"The scene folder has no {settings.priors} priors: choose another source"
        layout.label(text=text, icon=icon)
    _draw_priors(layout, priors)
    for part in settings_training.ESGS_PARTS:
        row = layout.row(align=True)
        row.prop(settings, part)
        weight = f"{part}_weight"
        if getattr(settings, part) and hasattr(settings, weight):
            row.prop(settings, weight, text="Weight")


def _draw_method_settings(layout: bpy.types.UILayout, settings, method: str) -> None:
    """Every setting of a method other than ESGS (none for plain 3DGS)."""
    settings_class = get_method(method).settings_class
    if settings_class is None:
        return
    box = layout.box()
    box.label(text=get_method(method).label)
    for name in property_values(settings, settings_class):
        box.prop(settings, name)


def _draw_priors(layout: bpy.types.UILayout, priors) -> None:
    """The prior-map computation beside the prior source: method, button, its job's progress."""
    if priors.status in ("pending", "running"):
        text = f"{priors.last_method or 'priors'}: {priors.step} / {priors.total} views"
        row = layout.row(align=True)
        row.progress(factor=priors.progress, type="BAR", text=text)
        row.operator("esgs.compute_priors_cancel", text="", icon="CANCEL")
        return
    row = layout.row(align=True)
    row.prop(priors, "method", text="")
    row.operator("esgs.compute_priors", icon="IMAGE_ZDEPTH")
    if priors.method == "ndn":
        layout.prop(priors, "ndn_weights")
    if priors.error:
        for index, line in enumerate(_wrap(f"Priors {priors.status}: {priors.error}", 48)):
            layout.label(text=line, icon="ERROR" if index == 0 else "NONE")
    elif priors.status == "finished":
        layout.label(text=f"Priors written: priors/{priors.last_method}", icon="CHECKMARK")


def _sentence(text: str) -> str:
    """``text`` with its first letter capitalised (``str.capitalize`` would lower "PSNR")."""
    return text[:1].upper() + text[1:]


def _wrap(text: str, width: int) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width) or [text]


CLASSES = (ESGS_PT_training,)
