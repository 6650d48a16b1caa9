"""ESGS > Synthetic Mars scene > Render dataset: a thin operator around ``render_dataset``."""
from __future__ import annotations

import bpy

from ..core.errors import ConfigError
from ._blocking import BlockingJobOperator


def find_scene_collection(context: bpy.types.Context) -> bpy.types.Collection:
    """The synthetic scene to render: the active collection if it is one, else the newest one."""
    from ..esgs_addon.terrain_scene import PROP_CONFIG

    layer = getattr(context, "view_layer", None)
    active = layer.active_layer_collection.collection if layer is not None else None
    if active is not None and PROP_CONFIG in active:
        return active
    candidates = [c for c in bpy.data.collections if PROP_CONFIG in c and context.scene.user_of_id(c)]
    if not candidates:
        raise ConfigError("there is no synthetic Mars scene to render", hint="press Generate first")
    return candidates[-1]


class ESGS_OT_render_dataset(BlockingJobOperator, bpy.types.Operator):
    """Render every camera of the synthetic scene with Cycles (CPU) and write the scene folder
    (images, COLMAP model, depth/normal/mask priors, ground-truth mesh), which Training then uses. Blocks until done"""

    bl_idname = "esgs.render_dataset"
    bl_label = "Render Dataset"
    bl_options = {"REGISTER"}

    def run_job(self, context, progress):
        from ..esgs_addon import training_job
        from ..esgs_addon.render_dataset import render_dataset
        from ..esgs_addon.terrain_scene import scene_objects_from_collection

        settings = context.scene.esgs.terrain
        if not settings.output_dir:
            raise ConfigError("choose an output folder first")
        objects = scene_objects_from_collection(find_scene_collection(context))
        out = render_dataset(objects, bpy.path.abspath(settings.output_dir), progress=progress,
                             sfm=settings.sfm, overwrite=settings.overwrite,
                             points_per_view=settings.points_per_view, scene=context.scene)
        training_job.use_for_training(context.scene, out)
        return f"Wrote scene folder {out}; Training now uses it"


CLASSES = (ESGS_OT_render_dataset,)
