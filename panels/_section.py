"""What every ESGS sidebar section shares: where it is drawn, its parent panel, and the
drawing of a settings group's properties."""
from __future__ import annotations

from typing import Any, Iterable


class ESGSSection:
    """Mixin for sub-panels of the ESGS sidebar tab (``class X(ESGSSection, bpy.types.Panel)``)."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ESGS"
    bl_parent_id = "ESGS_PT_main"


def prop_column(layout: Any, settings: Any, names: Iterable[str]) -> Any:
    """A new column in ``layout`` (a UILayout) with the properties ``names`` of ``settings``,
    one a line; returned so a panel can add more to it."""
    column = layout.column()
    for name in names:
        column.prop(settings, name)
    return column


def dependent_prop(layout: Any, settings: Any, name: str, *, active: bool) -> None:
    """The property ``name`` on a row of its own, greyed out (still editable) while the option
    it depends on is off, so the user sees it would have no effect."""
    row = layout.row()
    row.active = active
    row.prop(settings, name)
