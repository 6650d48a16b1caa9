"""Where a finished run's error on views with sky sits, and whether its sky model fits what it saw.

For a run folder and its scene (with ``priors/gt/mask``: 0 = sky), this writes:

- per view with more than 1 % sky (held-out and training): PSNR, the PSNR it would have with a
  perfect sky, and the share of its squared error in four regions: sky more than ``--band-px``
  pixels from the ground, sky within that band, ground within the band, ground beyond it;
- for the held-out views' sky pixels: the share within 1 degree of a training ray through sky
  (are they directions the training views saw?);
- the run's sky model alone against the training views' sky pixels (mean absolute colour
  error), and the same model family fitted directly to those pixels (Adam, ``--fit-steps``
  steps at the run's sky learning rate) at degrees 1-3 and with a 16-row grid: the error the
  representation allows.

Used for docs/benchmarks.md, "The sky's learning rate"::

    python benchmarks/sky_error_probe.py RUN_DIR SCENE_DIR --json benchmarks/results/sky_error_probe_....json
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

SKY_VIEW_FRACTION = 0.01


def _regions(mask: np.ndarray, band_px: int) -> dict[str, np.ndarray]:
    """Sky / ground pixels split at ``band_px`` pixels from the boundary (mask True = ground):
    :func:`~esgs.core.experiments.sky.horizon_band` from either side."""
    from esgs.core.experiments.sky import horizon_band

    ground_band, sky_band = horizon_band(mask, band_px), horizon_band(~mask, band_px)
    return {"sky_interior": ~mask & ~sky_band, "sky_band": sky_band,
            "ground_band": ground_band, "ground_interior": mask & ~ground_band}


def _psnr(mse: float) -> float:
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def view_rows(run_dir: Path, scene: Path, band_px: int) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Per-view error split of the views with sky, and the sky pixels' directions and colours."""
    from esgs.core.methods import run_renderer
    from esgs.core.priors.io import load_prior_maps
    from esgs.core.train.sky import ray_directions

    renderer = run_renderer(run_dir)
    rows, rays = [], {"train": ([], []), "test": ([], [])}
    for split in ("train", "test"):
        for view in renderer.views(split):
            mask = load_prior_maps(scene, "gt", view.name, size=(view.width, view.height)).mask.astype(bool)
            if (~mask).mean() <= SKY_VIEW_FRACTION:
                continue
            target = view.image_float(renderer.device)
            directions = ray_directions(view.viewmat, view.K, view.width, view.height)
            sky_pixels = torch.from_numpy(~mask)
            rays[split][0].append(directions[sky_pixels])
            rays[split][1].append(target.cpu()[sky_pixels])
            out = renderer.render(view)
            error = ((out.image.clamp(0, 1) - target) ** 2).mean(dim=-1).cpu().numpy()
            total = float(error.sum())
            row = {"split": split, "view": view.name, "sky_fraction": float((~mask).mean()),
                   "psnr": _psnr(float(error.mean())),
                   "psnr_with_perfect_sky": _psnr(float(np.where(mask, error, 0.0).mean())),
                   "error_share": {name: float(error[region].sum() / total) if total else 0.0
                                   for name, region in _regions(mask, band_px).items()}}
            rows.append(row)
    gathered = {split: (torch.cat(d) if d else torch.zeros(0, 3), torch.cat(c) if c else torch.zeros(0, 3))
                for split, (d, c) in rays.items()}
    return rows, {"sky": renderer.sky, "rays": gathered, "sky_lr": renderer.config.sky_lr}


def sky_fit(sky: Any, rays: dict[str, tuple[torch.Tensor, torch.Tensor]], sky_lr: float, steps: int) -> dict[str, Any]:
    """The run's sky against the training sky pixels, and direct fits of the same model family."""
    from esgs.core.train.sky import SkyModel, max_cosine

    directions, colours = rays["train"]
    test_directions = rays["test"][0]
    result: dict[str, Any] = {"train_sky_pixels": len(directions), "held_out_sky_pixels": len(test_directions)}
    if sky is None or not len(directions):
        return result
    with torch.no_grad():
        result["run_sky_mae_on_training_sky"] = float((sky(directions) - colours).abs().mean())
        if len(test_directions):
            cosine = torch.cat([max_cosine(chunk, directions) for chunk in test_directions.split(4096)])
            result["held_out_sky_within_1deg_of_training_sky"] = float(
                (cosine >= math.cos(math.radians(1.0))).float().mean())
    fits = {}
    for degree, grid_rows in ((1, 0), (2, 0), (3, 0), (3, 16)):
        model = SkyModel(degree, grid_rows=grid_rows)
        model.set_color(colours.mean(dim=0))
        optimizer = torch.optim.Adam(model.parameters(), lr=sky_lr)
        for _ in range(steps):
            optimizer.zero_grad()
            loss = (model(directions) - colours).abs().mean()
            loss.backward()
            optimizer.step()
        with torch.no_grad():
            fits[f"degree{degree}" + (f"_grid{grid_rows}" if grid_rows else "")] = float(
                (model(directions) - colours).abs().mean())
    result["direct_fit_mae_on_training_sky"] = fits
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("scene", type=Path)
    parser.add_argument("--band-px", type=int, default=4)
    parser.add_argument("--fit-steps", type=int, default=600)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    rows, extra = view_rows(args.run_dir, args.scene, args.band_px)
    fit = sky_fit(extra["sky"], extra["rays"], extra["sky_lr"], args.fit_steps)
    for row in rows:
        shares = " ".join(f"{k} {v:.2f}" for k, v in row["error_share"].items())
        print(f"{row['split']:5s} {row['view']}: {row['psnr']:.2f} dB (perfect sky {row['psnr_with_perfect_sky']:.2f}); {shares}")
    print({k: v for k, v in fit.items()})
    if args.json is not None:
        from esgs.core.io_utils import atomic_write_json

        atomic_write_json(args.json, {"command": " ".join(["python", "benchmarks/sky_error_probe.py", *sys.argv[1:]]),
                                      "run_dir": str(args.run_dir), "scene": str(args.scene),
                                      "band_px": args.band_px, "views": rows, "sky": fit})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
