"""The ``esgs colmap`` command: check, convert, undistort, and errors without tracebacks."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from esgs.core.cli import main
from esgs.core.colmap import read_model
from tests.conftest import require_shared
from tests.core.test_colmap_io import assert_models_equal


def make_scene(tmp_path: Path) -> Path:
    scene = tmp_path / "scene"
    shutil.copytree(require_shared("colmap_maupertuis", "sparse_bin"), scene / "sparse" / "0")
    shutil.copytree(require_shared("colmap_maupertuis", "images"), scene / "images")
    return scene


def test_check_prints_summary(tmp_path: Path, capsys) -> None:
    scene = make_scene(tmp_path)
    assert main(["colmap", "check", str(scene), "--sizes", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["images"], info["points"], info["observations"]) == (4, 1039, 3355)
    assert abs(info["mean_track_length"] - 3355 / 1039) < 1e-12
    assert info["cameras"] == {"1": "SIMPLE_PINHOLE 1919x1079"}


def test_check_reports_errors_without_traceback(tmp_path: Path, capsys) -> None:
    scene = make_scene(tmp_path)
    (scene / "images" / "01.jpg").unlink()
    assert main(["colmap", "check", str(scene)]) == 1  # bad data: exit status 1
    error = capsys.readouterr().err
    assert "01.jpg" in error and "Traceback" not in error


def test_convert_to_text_and_back(tmp_path: Path) -> None:
    scene = make_scene(tmp_path)
    assert main(["colmap", "convert", str(scene), str(tmp_path / "txt"), "--text"]) == 0
    assert (tmp_path / "txt" / "images.txt").is_file()
    assert_models_equal(read_model(tmp_path / "txt"), read_model(scene))


def test_undistort_pinhole_scene(tmp_path: Path) -> None:
    scene = make_scene(tmp_path)
    assert main(["colmap", "undistort", str(scene), str(tmp_path / "out")]) == 0
    model = read_model(tmp_path / "out")
    assert model.cameras[1].model == "PINHOLE"
    np.testing.assert_array_equal(model.cameras[1].params, [1847.53, 1847.53, 959.5, 539.5])
    # A pinhole camera needs no warp: the images are copied byte for byte.
    assert (tmp_path / "out" / "images" / "00.jpg").read_bytes() == (scene / "images" / "00.jpg").read_bytes()
