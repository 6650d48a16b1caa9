"""The main job end to end at toy size: every stage runs, the report carries real numbers."""
from __future__ import annotations

import json

import pytest

pytest.importorskip("bpy", reason="the demo's scene and Blender stages need the bpy module")


@pytest.mark.slow
def test_tiny_demo_runs_every_stage_and_reuses_finished_work(tmp_path):
    from esgs.core.demo import DemoConfig, run_demo

    events = []
    config = DemoConfig(out=tmp_path / "demo", views=4, width=96, height=54, samples=4, iterations=30,
                        snapshots=2, max_gaussians=4000)
    report = run_demo(config, progress=events.append)
    text = report.read_text()
    assert "| ESGS |" in text and "| 3DGS |" in text
    for name in ("curves.png", "geometry.png", "heat_map.png", "training_progress.png"):
        assert (tmp_path / "demo" / "report" / name).stat().st_size > 0, name
    assert (tmp_path / "demo" / "blender" / "results.blend").is_file()
    metrics = json.loads((tmp_path / "demo" / "runs" / "esgs" / "metrics.json").read_text())
    assert metrics["psnr"] > 8 and f"{metrics['psnr']:.2f}" in text
    saved = json.loads((tmp_path / "demo" / "runs" / "esgs" / "config.json").read_text())["esgs"]
    assert saved["depth"] and saved["gpdfn"] and saved["priors"] == "sfm"
    assert events[-1].kind == "done"
    # a second run reuses the scene and both finished runs
    again = []
    run_demo(config, progress=again.append)
    messages = " ".join(e.message for e in again if e.kind == "message")
    assert "reusing" in messages and "esgs: reusing finished run" in messages and "3dgs: reusing finished run" in messages
