"""ESGS > Synthetic Mars scene: thin operators around ``build_terrain_scene`` and ``render_dataset``."""
from __future__ import annotations

import bpy

from ._blocking import BlockingJobOperator


class ESGS_OT_generate_terrain(BlockingJobOperator, bpy.types.Operator):
    """Generate a synthetic Mars scene (terrain, rocks, sun, sky, cameras) in a new collection"""

    bl_idname = "esgs.generate_terrain"
    bl_label = "Generate Mars Scene"
    bl_options = {"REGISTER", "UNDO"}

    def run_job(self, context, progress):
        from ..esgs_addon.settings_terrain import job_from_properties
        from ..esgs_addon.terrain_scene import build_terrain_scene

        config = job_from_properties(context.scene.esgs.terrain).scene_config()
        objects = build_terrain_scene(config, scene=context.scene, progress=progress)
        return f"Generated '{objects['collection'].name}': {len(objects['rocks'])} rocks, {len(objects['cameras'])} cameras"


CLASSES = (ESGS_OT_generate_terrain,)
