"""File > Import / Export entries built by operators/_menu.py: one entry per operator module,
drawing its operator with its label, gone after unregistering."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

bpy = pytest.importorskip("bpy")

ENTRIES = [
    ("TOPBAR_MT_file_import", "esgs.operators.import_colmap", "esgs.import_colmap", "COLMAP Scene (ESGS)"),
    ("TOPBAR_MT_file_import", "esgs.operators.import_gaussians", "esgs.import_gaussians",
     "Gaussian Splats (.ply, ESGS)"),
    ("TOPBAR_MT_file_export", "esgs.operators.export_colmap", "esgs.export_colmap", "COLMAP Cameras (ESGS)"),
]


class RecordingLayout:
    def __init__(self):
        self.operators: list[tuple[str, str]] = []

    def operator(self, idname, text=""):
        self.operators.append((idname, text))


def entries_of(menu: str, module: str) -> list:
    return [f for f in getattr(bpy.types, menu)._dyn_ui_initialize() if f.__module__ == module]


@pytest.mark.parametrize("menu, module, idname, label", ENTRIES)
def test_each_operator_has_one_entry_drawing_it(menu, module, idname, label):
    (entry,) = entries_of(menu, module)
    menu_self = SimpleNamespace(layout=RecordingLayout())
    entry(menu_self, bpy.context)
    assert menu_self.layout.operators == [(idname, label)]
    assert hasattr(bpy.types, idname.replace("esgs.", "ESGS_OT_"))  # the operator it names is registered


def test_unregistering_removes_every_entry():
    import esgs

    esgs.unregister()
    try:
        for menu, module, _, _ in ENTRIES:
            assert entries_of(menu, module) == []
    finally:
        esgs.register()
    for menu, module, _, _ in ENTRIES:
        assert len(entries_of(menu, module)) == 1
