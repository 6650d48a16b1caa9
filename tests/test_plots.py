"""The report's plots (core/apps/plots.py): matplotlib figures, and the OpenCV fallback without it."""
import ast
import sys
from pathlib import Path

import numpy as np
import pytest

from esgs.core.apps import plots
from esgs.core.formats.imageio import read_image, write_png

CURVES = {"loss": {"ESGS": [(0, 0.5), (50, 0.2), (100, 0.1)], "3DGS": [(0, 0.6), (50, 0.3), (100, float("nan"))]},
          "psnr": {"ESGS": [(0, 12.0), (50, 18.0), (100, 21.5)], "3DGS": [(0, 11.0), (50, 16.0), (100, 19.0)]}}
SUMMARY = {"gaussians_to_mesh_filtered": {"p95": 0.0371}, "gaussians_to_mesh": {"p95": 0.09}, "threshold_m": 0.05}


def _hide_matplotlib(monkeypatch):
    for name in [n for n in sys.modules if n == "matplotlib" or n.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ImportError
    monkeypatch.setattr(plots, "_warned", False)


def test_curves_figure_has_axes_units_and_a_legend_per_method():
    pytest.importorskip("matplotlib")
    figure = plots.curves_figure(CURVES)
    loss, psnr = figure.axes[:2]
    assert (loss.get_xlabel(), loss.get_ylabel(), loss.get_yscale()) == ("step", "loss", "log")
    assert (psnr.get_xlabel(), psnr.get_ylabel()) == ("step", "PSNR (dB)")
    for ax in (loss, psnr):
        assert [text.get_text() for text in ax.get_legend().get_texts()] == ["ESGS", "3DGS"]


def test_curves_image_is_written_with_matplotlib(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    path = write_png(tmp_path / "curves.png", plots.curves_image(CURVES))
    image = read_image(path)
    assert 250 <= image.shape[0] <= 400 and 800 <= image.shape[1] <= 1100
    assert 5_000 < path.stat().st_size < 500_000
    assert "matplotlib is not installed" not in capsys.readouterr().out


def test_without_matplotlib_the_curves_fall_back_and_say_so_once(monkeypatch, capsys, tmp_path):
    _hide_matplotlib(monkeypatch)
    assert not plots.matplotlib_available()
    image = plots.curves_image(CURVES)
    heat = plots.heat_map_with_colour_bar(np.zeros((90, 160, 3), np.uint8), SUMMARY)
    assert image.dtype == np.uint8 and image.shape[0] == 240 and image.shape[1] > 900  # the OpenCV plots
    assert heat.shape[0] == 200 and heat.shape[1] > 160  # a bar at least 200 px tall
    write_png(tmp_path / "curves.png", image)
    assert capsys.readouterr().out.count("matplotlib is not installed") == 1


def test_heat_map_saturation_follows_the_blender_rule():
    assert plots.heat_map_saturation(SUMMARY) == (0.0371, "95th percentile")
    assert plots.heat_map_saturation({"gaussians_to_mesh_filtered": {"p95": None},
                                      "gaussians_to_mesh": {"p95": 0.09}})[0] == 0.09
    assert plots.heat_map_saturation({"threshold_m": 0.05}) == (0.05, "match threshold")


def test_colour_bar_is_labelled_with_the_percentile_in_metres():
    pytest.importorskip("matplotlib")
    figure = plots.colour_bar_figure(0.0371, "95th percentile", height_px=270)
    bar = figure.axes[0]
    labels = [tick.get_text() for tick in bar.get_yticklabels()]
    assert labels[0] == "0" and "0.0371" in labels[-1] and "95th" in labels[-1]
    assert "(m)" in bar.get_ylabel()
    render = np.full((270, 480, 3), 40, np.uint8)
    composed = plots.heat_map_with_colour_bar(render, SUMMARY)
    assert composed.shape[0] == 270 and composed.shape[1] > 480
    assert np.array_equal(composed[:, :480], render)  # the render's pixels are kept


def test_heat_stops_match_the_blender_ramp():
    # esgs_addon/gaussian_nodes imports bpy: read its HEAT_COLOURS from the source instead
    source = (Path(plots.__file__).parents[2] / "esgs_addon" / "gaussian_nodes.py").read_text()
    node = next(n for n in ast.walk(ast.parse(source))
                if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "HEAT_COLOURS")
    blender = ast.literal_eval(node.value)
    assert [(p, rgba[:3]) for p, rgba in blender] == [(p, rgb) for p, rgb in plots.HEAT_STOPS]
    assert np.allclose(plots.heat_colours(np.array([0.0, 1.0])), [[0, 0, 1], [1, 0, 0]])


def test_the_report_writes_the_curves_and_the_heat_map_with_its_bar(tmp_path):
    import json

    from esgs.core.apps.demo import DemoConfig
    from esgs.core.apps.report import write_report

    config = DemoConfig(out=tmp_path / "demo")
    for folder, psnr in (("esgs", 20.0), ("3dgs", 18.0)):
        run = config.out / "runs" / folder
        run.mkdir(parents=True)
        (run / "events.jsonl").write_text("\n".join(json.dumps(
            {"kind": "progress", "stage": "train", "step": step, "metrics": {"loss": 1.0 / step, "psnr": psnr + step / 10}})
            for step in (10, 20, 30)))
    (config.out / "blender").mkdir()
    render = write_png(config.out / "blender" / "heat_map.png", np.full((90, 160, 3), 128, np.uint8))
    blender = dict(SUMMARY, heat_map=str(render), blend=str(config.out / "blender" / "results.blend"))
    text = write_report(config, tmp_path / "scene", {}, {}, blender, {}).read_text()
    assert "![curves](report/curves.png)" in text and "![heat map](report/heat_map.png)" in text
    assert "red = 0.0371 m (the 95th percentile" in text
    assert read_image(config.out / "report" / "curves.png").shape[1] > 800
    heat = read_image(config.out / "report" / "heat_map.png")
    assert heat.shape[0] == 200 and heat.shape[1] > 160  # a bar at least 200 px tall
