"""What every ESGS sidebar section shares: where it is drawn and its parent panel."""
from __future__ import annotations


class ESGSSection:
    """Mixin for sub-panels of the ESGS sidebar tab (``class X(ESGSSection, bpy.types.Panel)``)."""


    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ESGS"
    bl_parent_id = "ESGS_PT_main"
