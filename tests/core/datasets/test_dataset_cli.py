"""The ``esgs dataset`` command: files written, errors printed without a traceback."""
from __future__ import annotations

import json

import numpy as np

from esgs.core.cli import main
from esgs.core.colmap import read_model
from esgs.core.formats.imageio import write_png


def test_from_panorama_writes_a_scene(panorama_file, tmp_path, capsys):
    code = main(["dataset", "from-panorama", str(panorama_file), "--out", str(tmp_path / "scene"),
                 "--size", "160x120", "--overlap", "0.3", "--fov-deg", "50", "--pitch-deg", "0", "--pitch-deg", "-20"])
    assert code == 0
    report = json.loads((tmp_path / "scene" / "panorama_report.json").read_text())
    model = read_model(tmp_path / "scene" / "sparse" / "0")
    assert len(model.images) == 2 * report["views_per_row"] == len(list((tmp_path / "scene" / "images").iterdir()))
    assert report["overlap"] >= 0.3 and report["rows"] == 2
    provenance = json.loads((tmp_path / "scene" / "scene.json").read_text())
    assert provenance["source"] == "panorama" and provenance["images"] == sorted(image.name for image in model.images.values())
    assert "wrote scene folder" in capsys.readouterr().out


def test_from_images_error_is_reported(tmp_path, capsys):
    write_png(tmp_path / "in" / "only.png", np.zeros((16, 16), np.uint8))
    assert main(["dataset", "from-images", str(tmp_path / "in"), "--out", str(tmp_path / "scene")]) == 1
    assert "needs at least 2 images, found 1" in capsys.readouterr().err
    assert not (tmp_path / "scene").exists()
