"""SfM (pycolmap) registers at least 90 % of the views of the presets that used to fail."""
from __future__ import annotations

import json

import pytest

pytest.importorskip("bpy")


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["dune_field", "navcam_panorama"])
def test_preset_renders_register_with_sfm(preset, tmp_path):
    from esgs.core.cli import main

    out = tmp_path / preset
    status = main(["scene", "--preset", preset, "--seed", "3", "--views", "12", "--resolution", "320x180",
                   "--samples", "8", "--sfm", "--out", str(out)])
    assert status == 0
    sfm = json.loads((out / "scene.json").read_text())["sfm"]
    assert sfm["total"] == 12
    assert sfm["registered"] / sfm["total"] >= 0.9
