"""File > Export > COLMAP cameras: a thin wrapper around ``export_cameras_to_colmap``."""
from __future__ import annotations

import bpy

from ..core.errors import ESGSError
from ..esgs_addon.colmap_scene import export_cameras_to_colmap
from ._menu import menu_hooks


class ESGS_OT_export_colmap(bpy.types.Operator):
    """Write the scene's cameras (at the render resolution) as a COLMAP model: PINHOLE cameras, images, empty points3D"""

    bl_idname = "esgs.export_colmap"
    bl_label = "Export COLMAP Cameras"
    bl_options = {"REGISTER"}

    directory: bpy.props.StringProperty(
        name="Model folder", description="Folder to write cameras, images and points3D into", subtype="DIR_PATH"
    )
    filter_folder: bpy.props.BoolProperty(default=True, options={"HIDDEN"})
    selected_only: bpy.props.BoolProperty(name="Selected only", description="Export only the selected cameras")
    binary: bpy.props.BoolProperty(name="Binary", description="Write .bin files (else .txt)", default=True)
    overwrite: bpy.props.BoolProperty(name="Overwrite", description="Replace a non-empty folder")

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        if self.selected_only:
            targets = [obj for obj in context.selected_objects if obj.type == "CAMERA"]
        else:
            targets = context.scene
        try:
            model = export_cameras_to_colmap(
                targets, self.directory, scene=context.scene, binary=self.binary, overwrite=self.overwrite
            )
        except ESGSError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Wrote {len(model.images)} cameras to {self.directory}")
        return {"FINISHED"}


CLASSES = (ESGS_OT_export_colmap,)
register_hooks, unregister_hooks = menu_hooks("TOPBAR_MT_file_export", ESGS_OT_export_colmap, "COLMAP Cameras (ESGS)")
