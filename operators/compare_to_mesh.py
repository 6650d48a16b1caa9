"""Measure the active Gaussian point cloud against a ground-truth mesh: wraps ``compare_to_mesh``."""
from __future__ import annotations

import bpy

from ..core.errors import ESGSError
from ..esgs_addon.compare_mesh import compare_to_mesh, describe
from ..esgs_addon.gaussians_import import is_gaussian_object


class ESGS_OT_compare_to_mesh(bpy.types.Operator):
    """Distances of the active Gaussians' centres to a mesh: statistics, precision/recall/F-score, heat map"""

    bl_idname = "esgs.compare_to_mesh"
    bl_label = "Compare to Mesh"
    bl_options = {"REGISTER", "UNDO"}

    mesh: bpy.props.StringProperty(
        name="Mesh", description="Name of the ground-truth mesh object (default: the panel's choice)")
    gaussians: bpy.props.StringProperty(
        name="Gaussians", description="Name of the Gaussian point cloud (default: the active object)")

    @classmethod
    def poll(cls, context):
        return True  # execute explains what is missing; a greyed-out button would not

    def execute(self, context):
        settings = context.scene.esgs.gaussians
        gaussians = bpy.data.objects.get(self.gaussians) if self.gaussians else context.active_object
        mesh = bpy.data.objects.get(self.mesh) if self.mesh else settings.mesh
        if not is_gaussian_object(gaussians):
            self.report({"ERROR"}, "Select an imported Gaussian point cloud (ESGS > Import Gaussians)")
            return {"CANCELLED"}
        if mesh is None:
            self.report({"ERROR"}, f"No mesh named '{self.mesh}'" if self.mesh else "Choose the ground-truth mesh")
            return {"CANCELLED"}
        try:
            summary = compare_to_mesh(gaussians, mesh, opacity_min=settings.compare_opacity_min,
                                      threshold_m=settings.threshold or None,
                                      n_surface_samples=settings.surface_samples,
                                      cameras="training" if settings.seen_surface_only else None,
                                      out_json=bpy.path.abspath(settings.report_path) if settings.report_path else None)
        except ESGSError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        except ImportError as error:
            # Blender's Python lacks scipy/trimesh unless the extension's wheels are installed
            self.report({"ERROR"}, f"The comparison needs {error.name or 'a missing package'}: {error}")
            return {"CANCELLED"}
        stats = summary["gaussians_to_mesh_filtered"]
        mean = f"{stats['mean']:.4g} m" if stats["mean"] is not None else "n/a"
        self.report({"INFO"}, f"Mean distance {mean} (opacity >= {settings.compare_opacity_min:g}); {describe(summary)}")
        return {"FINISHED"}


CLASSES = (ESGS_OT_compare_to_mesh,)
