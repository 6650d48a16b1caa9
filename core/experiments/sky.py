"""Measuring the sky fix: prior-loss artefacts at the sky boundary with and without masks.

The ground-truth priors of a synthetic scene mark sky as invalid *in the maps themselves*
(depth 0, normal (0, 0, 0)), so the losses skip it whatever the masks say. A dense
predictor (NDN, a monocular network) instead returns a depth and a normal for every pixel,
sky included, and only its mask says which pixels are surface. :func:`write_sky_filled_priors`
makes such a prior from gt: surface pixels exact, sky filled the way dense predictors
typically fill it (depth = the farthest surface depth of the view, i.e. a wall at the
horizon; normal facing the camera), mask = the gt mask. Training with it with
``use_masks`` on and off isolates what the masks do.

:func:`sky_figures` measures a finished run on its held-out views: PSNR on sky pixels and
on surface pixels, mean rendered alpha on the sky, and the relative depth error of surface
pixels in a band of ``band_px`` pixels below the horizon line (surface pixels within that
distance of a sky pixel), where a horizon wall would show first.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DatasetError
from ..formats.scene_dir import PriorSource, SceneDir


def write_sky_filled_priors(scene: str | Path, source: str = PriorSource.GT_SKYFILLED) -> int:
    """Write ``priors/<source>/`` from ``priors/gt/`` with the sky filled (module docstring); returns the view count."""
    from ..priors.io import load_prior_maps, write_prior_maps

    scene = Path(scene)
    depth_dir = SceneDir(scene).prior_maps(PriorSource.GT, "depth")
    if not depth_dir.is_dir():
        raise DatasetError("the scene has no gt depth priors", path=depth_dir, hint="make the scene with esgs scene")
    stems = sorted(path.stem for path in depth_dir.glob("*.exr"))
    for stem in stems:
        maps = load_prior_maps(scene, PriorSource.GT, stem + ".png")
        mask = maps.mask.astype(bool)
        depth = maps.depth.copy()
        normal = maps.normal.copy()
        far = float(depth[mask].max()) if mask.any() else 1.0
        depth[~mask] = far
        normal[~mask] = (0.0, 0.0, -1.0)
        write_prior_maps(scene, source, stem + ".png", depth=depth, normal=normal, mask=mask, mask_kind="surface",
                         metadata={"note": "gt with the sky filled: depth = farthest surface, normal facing the camera"})
    return len(stems)


def _psnr(rendered: np.ndarray, target: np.ndarray, where: np.ndarray) -> float | None:
    if not where.any():
        return None
    mse = float(((rendered[where] - target[where]) ** 2).mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def horizon_band(mask: np.ndarray, band_px: int) -> np.ndarray:
    """[H, W] bool: surface pixels (``mask`` True) within ``band_px`` pixels (chessboard) of a sky pixel."""
    import cv2

    sky = (~mask).astype(np.uint8)
    grown = cv2.dilate(sky, np.ones((2 * band_px + 1, 2 * band_px + 1), np.uint8))
    return mask & grown.astype(bool)


def sky_figures(run_dir: str | Path, scene: str | Path, *, band_px: int = 4) -> dict[str, Any]:
    """Sky-boundary figures of a finished run on its held-out views (module docstring).

    Returns {"psnr_sky", "psnr_surface", "alpha_sky", "horizon_depth_error", "views"}; the
    gt mask and depth are read from ``scene/priors/gt`` at the run's resolution.
    """
    from ..methods import run_renderer
    from ..priors.io import load_prior_maps

    renderer = run_renderer(run_dir)
    views = renderer.views("test") or renderer.views("train")
    sky_sq, sky_n, surface_sq, surface_n, alpha_sum, band_errors = 0.0, 0, 0.0, 0, 0.0, []
    for view in views:
        out = renderer.render(view, depth=True)
        maps = load_prior_maps(Path(scene), "gt", view.name, size=(view.width, view.height))
        mask = maps.mask.astype(bool)
        image = out.image.clamp(0, 1).cpu().numpy()
        target = view.image_float(renderer.device).cpu().numpy()  # [H, W, 3] in [0, 1]
        error = ((image - target) ** 2).mean(axis=-1)
        sky_sq += float(error[~mask].sum())
        sky_n += int((~mask).sum())
        surface_sq += float(error[mask].sum())
        surface_n += int(mask.sum())
        alpha_sum += float(out.alpha[..., 0].cpu().numpy()[~mask].sum())
        band = horizon_band(mask, band_px)
        if band.any():
            rendered = out.depth[..., 0].cpu().numpy()
            truth = maps.depth
            band_errors.append(np.abs(rendered[band] - truth[band]) / truth[band])

    def psnr(total: float, count: int) -> float | None:
        return None if count == 0 else 10.0 * math.log10(1.0 / max(total / count, 1e-12))
    errors = np.concatenate(band_errors) if band_errors else np.zeros(0)
    return {"psnr_sky": psnr(sky_sq, sky_n), "psnr_surface": psnr(surface_sq, surface_n),
            "alpha_sky": alpha_sum / sky_n if sky_n else None,
            "horizon_depth_error": float(np.median(errors)) if errors.size else None,
            "views": len(views), "sky_fraction": sky_n / max(sky_n + surface_n, 1)}
