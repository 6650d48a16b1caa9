"""The settings panels draw every property of their settings group, in order, greyed where
an option they depend on is off (drawn with a layout that records what would be shown)."""
from __future__ import annotations

import bpy
import pytest

from esgs.panels.import_panel import ESGS_PT_import
from esgs.panels.labels_panel import ESGS_PT_labels
from esgs.panels.terrain_panel import ESGS_PT_terrain


class RecordingLayout:
    """Stands in for a UILayout: records properties (with whether they are shown active),
    labels and operator buttons; rejects keywords and properties Blender would not accept."""

    def __init__(self, record: list, parent: "RecordingLayout | None" = None):
        self._record, self._parent = record, parent
        self.active = self.enabled = True

    def _active(self) -> bool:
        return self.active and (self._parent is None or self._parent._active())

    def _check(self, name: str, kwargs: dict) -> None:
        function = bpy.types.UILayout.bl_rna.functions[name]
        assert set(kwargs) <= {p.identifier for p in function.parameters}, (name, kwargs)

    def _child(self, name: str, **kwargs) -> "RecordingLayout":
        self._check(name, kwargs)
        return RecordingLayout(self._record, self)

    def column(self, **kwargs):
        return self._child("column", **kwargs)

    def row(self, **kwargs):
        return self._child("row", **kwargs)

    def box(self, **kwargs):
        return self._child("box", **kwargs)

    def prop(self, data, name: str, **kwargs) -> None:
        self._check("prop", kwargs)
        assert hasattr(data, name), name  # a misspelt property would show an error in Blender
        self._record.append(("prop", name, self._active()))

    def label(self, **kwargs) -> None:
        self._check("label", kwargs)
        self._record.append(("label", kwargs.get("text", "")))

    def operator(self, idname: str, **kwargs) -> None:
        self._check("operator", kwargs)
        self._record.append(("operator", idname))


def draw(panel_class) -> list:
    record: list = []
    panel = type("PanelStandIn", (), {"layout": RecordingLayout(record)})()
    panel_class.draw(panel, bpy.context)
    return record


@pytest.mark.parametrize("reconstruct", [False, True])
def test_labels_panel_greys_the_mesh_while_reconstructing(reconstruct):
    bpy.context.scene.esgs.labels.reconstruct = reconstruct
    assert draw(ESGS_PT_labels) == [("prop", "scene_dir", True), ("prop", "reconstruct", True),
                                    ("prop", "mesh_path", not reconstruct), ("operator", "esgs.render_labels")]


def test_terrain_panel_shows_generator_then_render_settings():
    assert draw(ESGS_PT_terrain) == [
        *[("prop", name, True) for name in ("preset", "palette", "config", "seed", "views", "width", "height",
                                                    "samples")],
        ("label", "0 keeps the preset's value"), ("operator", "esgs.generate_terrain"),
        *[("prop", name, True) for name in ("output_dir", "points_per_view", "sfm", "overwrite")],
        ("operator", "esgs.render_dataset")]


def test_import_panel_greys_options_of_what_is_not_imported():
    settings = bpy.context.scene.esgs.colmap_import
    settings.import_points, settings.image_planes = False, True
    record = draw(ESGS_PT_import)
    assert [entry[1] for entry in record if entry[0] == "prop"] == [
        "import_points", "point_radius", "image_planes", "image_plane_distance", "orient_up",
        "set_scene_resolution", "undistorted_path", "collection_name"]
    assert ("prop", "point_radius", False) in record and ("prop", "image_plane_distance", True) in record
    assert record[-2:] == [("operator", "esgs.import_colmap"), ("operator", "esgs.export_colmap")]
