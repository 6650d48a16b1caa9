"""ESGS > Synthetic Mars scene: thin operators around ``build_terrain_scene`` and ``render_dataset``."""
from __future__ import annotations

import bpy

from ..core.errors import ESGSError
from ..core.progress import ProgressEvent


def blender_progress(context: bpy.types.Context):
    """A progress callback driving Blender's progress indicator and printing messages."""
    window_manager = getattr(context, "window_manager", None)

    def report(event: ProgressEvent) -> None:
        if event.message:
            print(f"ESGS {event.stage}: {event.message}", flush=True)
        if window_manager is not None and event.total:
            window_manager.progress_update(int(100 * event.step / event.total))

    return report, window_manager


class ESGS_OT_generate_terrain(bpy.types.Operator):
    """Generate a synthetic Mars scene (terrain, rocks, sun, sky, cameras) in a new collection"""

    bl_idname = "esgs.generate_terrain"
    bl_label = "Generate Mars Scene"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        from ..esgs_addon.settings_terrain import job_from_properties
        from ..esgs_addon.terrain_scene import build_terrain_scene

        report, window_manager = blender_progress(context)
        if window_manager is not None:
            window_manager.progress_begin(0, 100)
        try:
            config = job_from_properties(context.scene.esgs.terrain).scene_config()
            objects = build_terrain_scene(config, scene=context.scene, progress=report)
        except ESGSError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        finally:
            if window_manager is not None:
                window_manager.progress_end()
        self.report({"INFO"}, f"Generated '{objects['collection'].name}': {len(objects['rocks'])} rocks, "
                              f"{len(objects['cameras'])} cameras")
        return {"FINISHED"}


CLASSES = (ESGS_OT_generate_terrain,)
