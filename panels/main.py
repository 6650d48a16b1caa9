"""The "ESGS" tab of the 3D View sidebar. Feature panels attach with ``bl_parent_id``."""
from __future__ import annotations

import bpy

ORDER = 0


class ESGS_PT_main(bpy.types.Panel):
    """Parent panel: every ESGS section is a sub-panel of this one."""

    bl_label = "ESGS"
    bl_idname = "ESGS_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ESGS"

    def draw(self, context: bpy.types.Context) -> None:
        # the add-on's own top package: ``esgs`` in a checkout, ``bl_ext.<repository>.esgs`` as
        # an installed extension (whose parent package has no version)
        from .. import __version__

        self.layout.label(text=f"ESGS for Blender {__version__}")


CLASSES = (ESGS_PT_main,)
