"""OpenCV drawing primitives shared by the report and its plots (no matplotlib needed)."""
from __future__ import annotations

import cv2
import numpy as np


def _rgb(image: np.ndarray) -> np.ndarray:
    return np.repeat(image[..., None], 3, axis=2) if image.ndim == 2 else image[..., :3]


def _hstack(images: list[np.ndarray], gap: int = 4) -> np.ndarray:
    height = max(i.shape[0] for i in images)
    padded = []
    for image in images:
        pad = np.zeros((height, image.shape[1] + gap, 3), np.uint8)
        pad[: image.shape[0], : image.shape[1]] = _rgb(image)
        padded.append(pad)
    return np.concatenate(padded, axis=1)[:, :-gap]


def plot_curves(series: dict[str, list[tuple[float, float]]], title: str, size: tuple[int, int] = (480, 240),
                log_y: bool = False) -> np.ndarray:
    """A minimal line plot (one colour per series) as an RGB image."""
    width, height = size
    image = np.full((height, width, 3), 255, np.uint8)
    left, right, top, bottom = 48, 10, 22, 24
    points = [p for values in series.values() for p in values if np.isfinite(p[1]) and (p[1] > 0 or not log_y)]
    cv2.putText(image, title, (left, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    if not points:
        return image
    xs = np.array([p[0] for p in points])
    ys = np.array([np.log10(p[1]) if log_y else p[1] for p in points])
    x_low, x_high = float(xs.min()), float(max(xs.max(), xs.min() + 1))
    y_low, y_high = float(ys.min()), float(max(ys.max(), ys.min() + 1e-6))
    cv2.rectangle(image, (left, top), (width - right, height - bottom), (0, 0, 0), 1)
    for value, label in ((y_low, y_low), (y_high, y_high)):
        y = int(height - bottom - (value - y_low) / (y_high - y_low) * (height - top - bottom))
        text = f"{10 ** label:.3g}" if log_y else f"{label:.3g}"
        cv2.putText(image, text, (2, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(image, f"step {int(x_high)}", (width - right - 70, height - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.33,
                (0, 0, 0), 1, cv2.LINE_AA)
    colours = [(200, 40, 40), (40, 90, 200), (40, 160, 60), (160, 60, 160)]
    for index, (name, values) in enumerate(series.items()):
        pts = [(x, np.log10(y) if log_y else y) for x, y in values if np.isfinite(y) and (y > 0 or not log_y)]
        if len(pts) < 2:
            continue
        poly = np.array([[left + (x - x_low) / (x_high - x_low) * (width - left - right),
                          height - bottom - (y - y_low) / (y_high - y_low) * (height - top - bottom)] for x, y in pts])
        cv2.polylines(image, [poly.astype(np.int32)], False, colours[index % 4][::-1], 1, cv2.LINE_AA)
        cv2.putText(image, name, (left + 6 + 70 * index, top + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    colours[index % 4][::-1], 1, cv2.LINE_AA)
    return image
