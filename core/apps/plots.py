"""The report's plots: training curves and the distance heat map's colour bar.

matplotlib is an optional dependency (``make setup`` installs it, see requirements.txt). It is
imported lazily and used through its object-oriented API with the Agg canvas, so no global
backend is chosen for the process (Blender included). Without it the pictures are drawn with
OpenCV as before (:func:`esgs.core.apps.drawing.plot_curves`, a plain bar) and one message says so.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np

# The heat map's colour ramp: (position, RGB) stops from 0 (blue) to the saturation distance
# (red), as esgs_addon/gaussian_nodes.HEAT_COLOURS builds it in Blender (core never imports bpy;
# tests/test_plots.py keeps the two equal).
HEAT_STOPS = ((0.0, (0.0, 0.0, 1.0)), (0.25, (0.0, 1.0, 1.0)), (0.5, (0.0, 1.0, 0.0)),
              (0.75, (1.0, 1.0, 0.0)), (1.0, (1.0, 0.0, 0.0)))
HEAT_PERCENTILE = 95  # the heat map saturates (red) at this percentile of the distances

METHOD_COLOURS = {"ESGS": "tab:red", "3DGS": "tab:blue"}

_warned = False


def matplotlib_available() -> bool:
    """True when matplotlib imports; otherwise prints, once per process, that the plots fall back."""
    global _warned
    try:
        import matplotlib  # noqa: F401
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
        return True
    except ImportError:
        if not _warned:
            _warned = True
            print("note: matplotlib is not installed; the report's plots are drawn without axes labels "
                  "(pip install matplotlib, or make setup)", flush=True)
        return False


def _figure(width_px: int, height_px: int, dpi: int = 100) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width_px / dpi, height_px / dpi), dpi=dpi)
    FigureCanvasAgg(figure)
    return figure


def figure_to_rgb(figure: Any) -> np.ndarray:
    """The figure drawn by its Agg canvas as an RGB uint8 array [H, W, 3]."""
    figure.canvas.draw()
    return np.asarray(figure.canvas.buffer_rgba())[..., :3].copy()


# --------------------------------------------------------------------------- training curves

def curves_figure(curves: dict[str, dict[str, list[tuple[float, float]]]], size: tuple[int, int] = (960, 320)) -> Any:
    """Loss and PSNR against the training step, one line per method; a matplotlib Figure.

    ``curves``: ``{"loss": {method: [(step, value), ...]}, "psnr": {...}}`` (either key may be
    missing). Loss is drawn on a log axis; non-finite values (and loss <= 0) are left out.
    """
    figure = _figure(*size)
    axes = figure.subplots(1, 2)
    panels = (("loss", "training loss (smoothed)", "loss", True),
              ("psnr", "training PSNR (smoothed)", "PSNR (dB)", False))
    for ax, (key, title, ylabel, log_y) in zip(axes, panels):
        drawn = False
        for name, values in (curves.get(key) or {}).items():
            points = [(x, y) for x, y in values if np.isfinite(y) and (y > 0 or not log_y)]
            if not points:
                continue
            xs, ys = zip(*points)
            ax.plot(xs, ys, label=name, color=METHOD_COLOURS.get(name), linewidth=1.2)
            drawn = True
        if log_y and drawn:
            ax.set_yscale("log")
        ax.set_title(title)
        ax.set_xlabel("step")
        ax.set_ylabel(ylabel)
        ax.grid(True, alpha=0.3)
        if drawn:
            ax.legend(title="method")
        else:
            ax.text(0.5, 0.5, "no values recorded", ha="center", va="center", transform=ax.transAxes)
    figure.tight_layout()
    return figure


def curves_image(curves: dict[str, dict[str, list[tuple[float, float]]]]) -> np.ndarray:
    """The training curves as an RGB image: matplotlib's :func:`curves_figure` when it is
    installed, else the OpenCV line plots the report drew before (no axis labels)."""
    if matplotlib_available():
        return figure_to_rgb(curves_figure(curves))
    from .drawing import _hstack, plot_curves

    return _hstack([plot_curves(curves.get(key) or {}, f"training {key} (smoothed)", log_y=key == "loss")
                    for key in ("loss", "psnr")])


# --------------------------------------------------------------------------- heat-map colour bar

def heat_map_saturation(summary: dict[str, Any]) -> tuple[float, str]:
    """The distance (metres) at which the heat map turns red, and what it is.

    The rule of esgs_addon/compare_mesh.compare_to_mesh: the 95th percentile of the filtered
    Gaussian-to-mesh distances, else of all of them, else the match threshold.
    """
    for key, what in (("gaussians_to_mesh_filtered", f"{HEAT_PERCENTILE}th percentile"),
                      ("gaussians_to_mesh", f"{HEAT_PERCENTILE}th percentile, unfiltered")):
        value = (summary.get(key) or {}).get("p95")
        if value:
            return float(max(value, 1e-9)), what
    return float(max(summary.get("threshold_m") or 1e-9, 1e-9)), "match threshold"


def heat_colours(values: np.ndarray) -> np.ndarray:
    """RGB floats in [0, 1] of the heat ramp at ``values`` in [0, 1] (linear between stops)."""
    positions = np.array([p for p, _ in HEAT_STOPS])
    rgb = np.array([c for _, c in HEAT_STOPS])
    values = np.clip(np.asarray(values, dtype=np.float64), 0, 1)
    return np.stack([np.interp(values, positions, rgb[:, i]) for i in range(3)], axis=-1)


def colour_bar_figure(saturation_m: float, what: str = f"{HEAT_PERCENTILE}th percentile", height_px: int = 270,
                      width_px: int = 150) -> Any:
    """A vertical colour bar of the heat map in metres, 0 (blue) to ``saturation_m`` (red), its
    top tick labelled with the value and ``what`` it is; a matplotlib Figure."""
    from matplotlib.colorbar import ColorbarBase
    from matplotlib.colors import LinearSegmentedColormap, Normalize

    figure = _figure(width_px, height_px)
    ax = figure.add_axes((0.12, 0.06, 0.16, 0.82))
    cmap = LinearSegmentedColormap.from_list("esgs_heat", list(HEAT_STOPS))
    bar = ColorbarBase(ax, cmap=cmap, norm=Normalize(0.0, saturation_m), orientation="vertical")
    ticks = [0.0, saturation_m / 2, saturation_m]
    bar.set_ticks(ticks)
    short = what.split(",")[0].replace("th percentile", "th pct")
    bar.set_ticklabels(["0", f"{saturation_m / 2:.3g}", f"{saturation_m:.3g}\n({short})"])
    bar.ax.tick_params(labelsize=8)
    bar.set_label("distance to mesh (m)", fontsize=8)
    return figure


def _colour_bar_fallback(saturation_m: float, height: int, width: int = 150) -> np.ndarray:
    image = np.full((height, width, 3), 255, np.uint8)
    top, bottom, left, bar_width = 18, 10, 8, 18
    span = max(height - top - bottom, 2)
    colours = heat_colours(np.linspace(1, 0, span))
    image[top:top + span, left:left + bar_width] = (colours[:, None, :] * 255).round().astype(np.uint8)
    font, black = cv2.FONT_HERSHEY_SIMPLEX, (0, 0, 0)
    cv2.putText(image, f"{saturation_m:.3g} m (p{HEAT_PERCENTILE})", (left + bar_width + 4, top + 8), font, 0.35,
                black, 1, cv2.LINE_AA)
    cv2.putText(image, "0 m", (left + bar_width + 4, top + span), font, 0.35, black, 1, cv2.LINE_AA)
    cv2.putText(image, "distance", (left, 12), font, 0.35, black, 1, cv2.LINE_AA)
    return image


def heat_map_with_colour_bar(render: np.ndarray, summary: dict[str, Any]) -> np.ndarray:
    """The Blender heat-map render with its colour bar (metres) to the right, as one RGB image."""
    render = np.repeat(render[..., None], 3, axis=2) if render.ndim == 2 else render[..., :3]
    if render.dtype != np.uint8:
        render = (np.clip(render, 0, 1) * 255).round().astype(np.uint8)
    saturation, what = heat_map_saturation(summary)
    height = max(render.shape[0], 200)  # a readable bar beside a small render: white below the render
    if render.shape[0] < height:
        render = np.concatenate([render, np.full((height - render.shape[0], *render.shape[1:]), 255, np.uint8)])
    if matplotlib_available():
        bar = figure_to_rgb(colour_bar_figure(saturation, what, height_px=height))[:height]
    else:
        bar = _colour_bar_fallback(saturation, height)
    return np.concatenate([render, bar], axis=1)


def write_heat_map(render_path: Path, summary: dict[str, Any], out_path: Path) -> Optional[tuple[float, str]]:
    """Write the render with its colour bar to ``out_path``; returns (saturation metres, what)."""
    from ..formats.imageio import read_image, write_png

    write_png(out_path, heat_map_with_colour_bar(read_image(render_path), summary))
    return heat_map_saturation(summary)
