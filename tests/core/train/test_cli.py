"""``esgs train``, ``esgs eval`` and ``esgs render`` from the command line (in-process)."""
from __future__ import annotations

import json

import numpy as np

from esgs.core.cli import main


def test_train_eval_render(tiny_scene, tmp_path, capsys):
    run = tmp_path / "run"
    code = main(["train", str(tiny_scene), "--out", str(run), "--iterations", "6", "--backend", "reference",
                 "--threads", "1", "--no-lpips", "--quiet", "--seed", "3", "--resolution", "2"])
    out = capsys.readouterr().out
    assert code == 0 and "completed: 6 steps" in out and "test PSNR" in out
    config = json.loads((run / "config.json").read_text())
    assert config["seed"] == 3 and config["resolution"] == 2 and config["iterations"] == 6

    assert main(["eval", str(run), "--no-lpips", "--json"]) == 0
    metrics = json.loads(capsys.readouterr().out)
    assert metrics["views_count"] == 2 and metrics["lpips"] is None
    # eval re-renders from the PLY (full SH degree): the same numbers as the end of training
    stored = json.loads((run / "metrics.json").read_text())
    assert np.isclose(metrics["psnr"], stored["psnr"], atol=1e-3)

    assert main(["render", str(run), "--camera", "view_003", "--depth"]) == 0
    written = capsys.readouterr().out.split()
    assert [p.rsplit("/", 1)[-1] for p in written] == ["view_003.png", "view_003_depth.exr"]
    from esgs.core.formats.imageio import read_image

    assert read_image(run / "renders" / "cameras" / "view_003.png").shape == (12, 16, 3)
    assert main(["render", str(run), "--all"]) == 0
    assert len(capsys.readouterr().out.split()) == 10


def test_errors_are_reported_without_traceback(tiny_scene, tmp_path, capsys):
    assert main(["train", str(tmp_path / "missing"), "--out", str(tmp_path / "run"), "--backend", "reference"]) == 1
    assert "scene folder not found" in capsys.readouterr().err
    assert main(["render", str(tmp_path / "run2"), "--all"]) == 1
    assert "not a run folder" in capsys.readouterr().err
