"""Sidebar > ESGS > Gaussians: import trained Gaussians, their display, and the mesh comparison."""
from __future__ import annotations

import bpy

from ._section import ESGSSection, prop_column

from ..esgs_addon import gaussian_nodes
from ..esgs_addon.compare_mesh import last_comparison
from ..esgs_addon.gaussians_import import is_gaussian_object

ORDER = 120  # after the training panel

_DISPLAY = ("Ellipsoids", "Opacity Min", "Max Display", "Point Radius", "Ellipsoid Size")
_HEAT = ("Heat Map", "Distance Min", "Distance Max")


class ESGS_PT_results(ESGSSection, bpy.types.Panel):
    """Trained Gaussians: import, display, and distances to a ground-truth mesh."""

    bl_label = "Gaussians"
    bl_idname = "ESGS_PT_results"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        settings = context.scene.esgs.gaussians
        prop_column(layout, settings, ("mode", "opacity_min", "max_display", "keep_sh"))
        layout.operator("esgs.import_gaussians", icon="IMPORT")

        obj = context.active_object
        if not is_gaussian_object(obj):
            layout.label(text="Select imported Gaussians to see more", icon="INFO")
            return
        modifier = obj.modifiers.get(gaussian_nodes.MODIFIER_NAME)
        if modifier is not None and modifier.node_group is not None:
            identifiers = gaussian_nodes.input_identifiers(modifier.node_group)
            box = layout.box()
            box.label(text=f"{obj.name}: {len(obj.data.points):,} Gaussians", icon="POINTCLOUD_DATA")
            for name in _DISPLAY + (_HEAT if "distance" in obj.data.attributes else ()):
                if name in identifiers:
                    box.prop(modifier, f'["{identifiers[name]}"]', text=name)

        box = layout.box()
        box.label(text="Compare to mesh", icon="MOD_MESHDEFORM")
        box.prop(settings, "mesh")
        box.prop(settings, "compare_opacity_min")
        box.prop(settings, "threshold")
        if settings.threshold == 0:
            box.label(text="Threshold 0: scaled to the scene (1% of the viewing distance)", icon="INFO")
        box.prop(settings, "seen_surface_only")
        box.prop(settings, "surface_samples")
        box.prop(settings, "report_path")
        box.operator("esgs.compare_to_mesh", icon="DRIVER_DISTANCE")

        summary = last_comparison(obj)
        if summary:
            draw_summary(layout.box(), summary)


def draw_summary(layout: bpy.types.UILayout, summary: dict) -> None:
    """The statistics of a comparison: distances both ways and the scores."""
    layout.label(text=f"Against '{summary.get('mesh', '?')}' ({summary.get('frame', '')})")
    sections = (
        (f"Gaussians -> mesh (opacity >= {summary.get('opacity_min') or 0:g}, "
         f"{summary.get('n_gaussians_filtered', 0):,})", summary.get("gaussians_to_mesh_filtered")),
        (f"Gaussians -> mesh (all {summary.get('n_gaussians', 0):,})", summary.get("gaussians_to_mesh")),
        ("Mesh -> Gaussians", summary.get("mesh_to_gaussians")),
    )
    for title, stats in sections:
        if not stats or stats.get("mean") is None:
            continue
        layout.label(text=title)
        grid = layout.grid_flow(columns=3, even_columns=True)
        for key in ("mean", "std", "median", "p95", "rms", "max"):
            grid.label(text=f"{key} {stats[key]:.4g}")
    if summary.get("fscore") is None:
        layout.label(text=f"No Gaussian at opacity >= {summary.get('opacity_min') or 0:g}: scores undefined, "
                          "lower the opacity filter", icon="ERROR")
    else:
        layout.label(text=f"At {summary.get('threshold_m', 0):.4g} m: precision {summary['precision']:.3f}, "
                          f"recall {summary['recall']:.3f}, F {summary['fscore']:.3f}")
    rule = summary.get("threshold_rule")
    if rule and rule != "given":
        layout.label(text=f"Threshold: {rule}")
    if summary.get("n_visible_samples") is not None:
        layout.label(text=f"Recall over the {summary.get('visible_fraction', 0):.0%} of the mesh the "
                          f"{summary.get('n_cameras', 0)} training cameras saw", icon="HIDE_OFF")
        if summary.get("recall_whole_mesh") is not None:
            layout.label(text=f"(whole mesh: recall {summary['recall_whole_mesh']:.3f})")
    else:
        layout.label(text="Recall over the whole mesh (no training cameras known)", icon="INFO")
    if summary.get("legend"):
        layout.label(text=f"Heat map legend: '{summary['legend']}' (metres)", icon="COLOR")


CLASSES = (ESGS_PT_results,)
