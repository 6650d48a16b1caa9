"""Settings for importing trained Gaussians and comparing them with a mesh: ``scene.esgs.gaussians``."""
from __future__ import annotations

import bpy

from .properties import settings_group


def _is_mesh(self, obj: bpy.types.Object) -> bool:
    return obj.type == "MESH"


@settings_group("gaussians")
class ESGS_PG_gaussians(bpy.types.PropertyGroup):
    """Import options of ``esgs.import_gaussians`` and options of ``esgs.compare_to_mesh``."""

    mode: bpy.props.EnumProperty(
        name="Display",
        items=(("points", "Points", "One sphere of fixed radius per Gaussian (fast)"),
               ("ellipsoids", "Ellipsoids", "One ellipsoid per Gaussian, scaled and rotated like it")),
        default="points",
    )
    opacity_min: bpy.props.FloatProperty(
        name="Opacity min", description="Hide Gaussians whose opacity is below this (they stay in the data)",
        default=0.0, min=0.0, max=1.0)
    max_display: bpy.props.IntProperty(
        name="Max shown", description="Show at most about this many Gaussians (a random subset)",
        default=1_000_000, min=0)
    keep_sh: bpy.props.BoolProperty(
        name="Keep SH coefficients", description="Also store the raw spherical-harmonic coefficients", default=False)

    mesh: bpy.props.PointerProperty(
        name="Ground truth", description="Mesh to measure the Gaussian centres against", type=bpy.types.Object,
        poll=_is_mesh)
    compare_opacity_min: bpy.props.FloatProperty(
        name="Opacity min", description="Gaussians below this opacity are left out of the filtered figures",
        default=0.5, min=0.0, max=1.0)
    threshold: bpy.props.FloatProperty(
        name="Threshold", description="Distance under which a point counts as matched (precision, recall). "
        "0: scale with the scene, 1% of the median distance from the training cameras to the surface they saw "
        "(without cameras 0.5% of the mesh's bounding-box diagonal)",
        default=0.0, min=0.0, subtype="DISTANCE", precision=4)
    seen_surface_only: bpy.props.BoolProperty(
        name="Seen surface only", description="Count recall and completeness only over the part of the mesh the "
        "training cameras of the Gaussians' run saw (in a camera's view and not hidden); off: the whole mesh",
        default=True)
    surface_samples: bpy.props.IntProperty(
        name="Surface samples", description="Points sampled on the mesh for completeness and recall",
        default=100_000, min=100)
    report_path: bpy.props.StringProperty(
        name="Report", description="Write the comparison as JSON here (optional)", subtype="FILE_PATH")
