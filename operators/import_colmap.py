"""File > Import > COLMAP scene: a thin wrapper around ``import_colmap_scene``."""
from __future__ import annotations

import bpy

from ..core.errors import ESGSError
from ..esgs_addon import training_job
from ..esgs_addon.colmap_scene import import_colmap_scene
from ..esgs_addon.settings_colmap_import import options_from_properties
from ._menu import menu_hooks


class ESGS_OT_import_colmap(bpy.types.Operator):
    """Import a COLMAP scene (cameras, sparse points, optional image planes) into a new collection"""

    bl_idname = "esgs.import_colmap"
    bl_label = "Import COLMAP Scene"
    bl_options = {"REGISTER", "UNDO"}

    directory: bpy.props.StringProperty(
        name="Scene folder",
        description="Scene folder holding images/ and sparse/0, or the COLMAP model folder itself",
        subtype="DIR_PATH",
    )
    filter_folder: bpy.props.BoolProperty(default=True, options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def draw(self, context):
        settings = context.scene.esgs.colmap_import
        for name in settings.__annotations__:
            self.layout.prop(settings, name)

    def execute(self, context):
        options = options_from_properties(context.scene.esgs.colmap_import)
        try:
            result = import_colmap_scene(self.directory, options, scene=context.scene)
        except ESGSError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        folder = training_job.scene_dir_of_collection(result["collection"])
        if folder is not None:
            training_job.use_for_training(context.scene, folder)
        for warning in result["warnings"]:
            self.report({"WARNING"}, warning)
        if result["image_planes"]:
            show_textures_in_solid_view(context)
        points = result["points"]
        count = len(points.data.points) if points is not None else 0
        self.report(
            {"INFO"},
            f"Imported '{result['collection'].name}': {len(result['cameras'])} cameras, {count} points",
        )
        return {"FINISHED"}


def show_textures_in_solid_view(context) -> None:
    """Solid view shows image textures only in 'Texture' colour mode; switch the open 3D views
    still on the default 'Material' mode so the image planes show their photos."""
    screen = getattr(context, "screen", None)
    for area in screen.areas if screen is not None else ():
        if area.type == "VIEW_3D":
            shading = area.spaces.active.shading
            if shading.type == "SOLID" and shading.color_type == "MATERIAL":
                shading.color_type = "TEXTURE"


CLASSES = (ESGS_OT_import_colmap,)
register_hooks, unregister_hooks = menu_hooks("TOPBAR_MT_file_import", ESGS_OT_import_colmap, "COLMAP Scene (ESGS)")
