"""``esgs labels``: arguments and the clear errors it gives before any rendering starts."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.cli import main
from esgs.core.colmap import Camera, ColmapModel, write_model
from esgs.core.errors import ConfigError, DatasetError
from esgs.core.labels.pipeline import LabelJob, run_label_job

from .synthetic_views import write_scene


def test_mesh_and_reconstruct_exclude_each_other(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["labels", str(tmp_path), "--mesh", "m.ply", "--reconstruct"])
    with pytest.raises(SystemExit):
        main(["labels", str(tmp_path)])
    with pytest.raises(ConfigError, match="exactly one"):
        LabelJob(scene=tmp_path).validate()


def test_missing_mesh_is_reported_and_nothing_is_written(tmp_path, capsys):
    write_scene(tmp_path, 2)
    status = main(["labels", str(tmp_path), "--mesh", str(tmp_path / "nowhere.ply")])
    error = capsys.readouterr().err
    assert status != 0 and "mesh file not found" in error and "nowhere.ply" in error
    assert not (tmp_path / "priors").exists() and not list(tmp_path.glob(".labels*"))


def test_scene_without_cameras_is_reported(tmp_path):
    model = ColmapModel({1: Camera(1, "PINHOLE", 8, 6, np.array([5.0, 5.0, 4.0, 3.0]))}, {}, {})
    write_model(model, tmp_path / "sparse" / "0")
    (tmp_path / "mesh.ply").write_text("ply\n")
    with pytest.raises(DatasetError, match="no registered images|no images"):
        run_label_job(LabelJob(scene=tmp_path, mesh=tmp_path / "mesh.ply"))
    with pytest.raises(DatasetError, match="no COLMAP model|not found"):
        run_label_job(LabelJob(scene=tmp_path / "missing", reconstruct=True))


def test_distorted_cameras_are_refused(tmp_path):
    from esgs.core.colmap import read_model

    write_scene(tmp_path, 2)
    model = read_model(tmp_path)
    camera = model.cameras[1]
    model.cameras[1] = Camera(1, "SIMPLE_RADIAL", camera.width, camera.height, np.array([80.0, 48.0, 32.0, 0.01]))
    write_model(model, tmp_path / "sparse" / "0", overwrite=True)
    (tmp_path / "mesh.ply").write_text("ply\n")
    with pytest.raises(DatasetError, match="lens distortion.*SIMPLE_RADIAL"):
        run_label_job(LabelJob(scene=tmp_path, mesh=tmp_path / "mesh.ply"))


def test_report_needs_ground_truth(tmp_path):
    write_scene(tmp_path, 2)
    (tmp_path / "mesh.ply").write_text("ply\n")
    with pytest.raises(DatasetError, match="priors/gt"):
        run_label_job(LabelJob(scene=tmp_path, mesh=tmp_path / "mesh.ply", report=True))


def test_bad_stereo_settings_are_config_errors(tmp_path):
    write_scene(tmp_path, 2)
    status = main(["labels", str(tmp_path), "--reconstruct", "--stereo-window-px", "4"])
    assert status != 0
    assert not (tmp_path / "mesh").exists()


@pytest.mark.parametrize("through_gap, expected", [(0.03, "3.00 % dropped, seen through gaps"), (None, None)])
def test_the_summary_line_counts_labels_dropped_as_seen_through_gaps(tmp_path, capsys, monkeypatch, through_gap,
                                                                      expected):
    from esgs.core.labels import pipeline

    view = {"image": "a.png", "rendered_fraction": 0.9, "filled_fraction": 0.01, "empty_fraction": 0.09}
    if through_gap is not None:
        view["through_gap_fraction"] = through_gap  # labels.json before the gap rule has no such key

    def fake_job(job, progress, verbose=False):
        return {"labels": {"views": [view]}, "reconstruction": None, "accuracy": None}

    monkeypatch.setattr(pipeline, "run_label_job", fake_job)
    assert main(["labels", str(tmp_path), "--reconstruct"]) == 0
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "filled 1.00 % of pixels, no label 9.00 %" in line
    assert (expected in line) if expected else ("gaps" not in line)
