"""File > Import > Gaussian Splats (3DGS PLY): a thin wrapper around ``import_gaussians``."""
from __future__ import annotations

import bpy
from bpy_extras.io_utils import ImportHelper

from ..core.errors import ESGSError
from ..esgs_addon.gaussians_import import import_gaussians
from ._menu import menu_hooks


class ESGS_OT_import_gaussians(bpy.types.Operator, ImportHelper):
    """Import trained Gaussians (3D Gaussian Splatting PLY) as a point cloud"""

    bl_idname = "esgs.import_gaussians"
    bl_label = "Import Gaussians"
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ".ply"
    filter_glob: bpy.props.StringProperty(default="*.ply", options={"HIDDEN"})

    def draw(self, context):
        settings = context.scene.esgs.gaussians
        for name in ("mode", "opacity_min", "max_display", "keep_sh"):
            self.layout.prop(settings, name)

    def execute(self, context):
        settings = context.scene.esgs.gaussians
        try:
            obj = import_gaussians(self.filepath, opacity_min=settings.opacity_min, max_display=settings.max_display,
                                   mode=settings.mode, keep_sh=settings.keep_sh)
        except ESGSError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        for other in context.view_layer.objects:
            other.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        self.report({"INFO"}, f"Imported {len(obj.data.points):,} Gaussians as '{obj.name}'")
        return {"FINISHED"}


CLASSES = (ESGS_OT_import_gaussians,)
register_hooks, unregister_hooks = menu_hooks("TOPBAR_MT_file_import", ESGS_OT_import_gaussians,
                                              "Gaussian Splats (.ply, ESGS)")
