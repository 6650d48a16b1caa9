"""benchmarks/sky_error_probe.py: the error regions of a view with sky, and the sky fits."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.core.experiments.helpers import load_benchmark_script


def load_probe():
    return load_benchmark_script("sky_error_probe")


def test_the_four_regions_split_the_image_at_the_band_around_the_horizon():
    probe = load_probe()
    mask = np.ones((20, 30), dtype=bool)
    mask[:8] = False  # sky in the top 8 rows, ground below
    regions = probe._regions(mask, band_px=2)
    stacked = np.stack(list(regions.values())).astype(int)
    assert (stacked.sum(axis=0) == 1).all()  # disjoint, and every pixel in one
    rows = {name: sorted(set(np.nonzero(region)[0])) for name, region in regions.items()}
    assert rows == {"sky_interior": list(range(0, 6)), "sky_band": [6, 7], "ground_band": [8, 9],
                    "ground_interior": list(range(10, 20))}


def test_the_run_sky_error_and_the_direct_fits_are_measured_against_the_training_sky():
    from esgs.core.train.sky import SkyModel, fibonacci_sphere

    probe = load_probe()
    truth = SkyModel(degree=1, initial_color=(0.7, 0.5, 0.3))
    with torch.no_grad():
        truth.coefficients[1] = torch.tensor([0.6, 0.6, 0.6])  # brighter towards +z
    directions = fibonacci_sphere(2000)
    directions = directions[directions[:, 2] > 0.1]  # an upper band of the sphere, as views see sky
    with torch.no_grad():
        colours = truth(directions)
    held_out = directions[:50]
    rays = {"train": (directions, colours), "test": (held_out, colours[:50])}
    result = probe.sky_fit(truth, rays, sky_lr=0.05, steps=300)
    assert result["run_sky_mae_on_training_sky"] == pytest.approx(0.0, abs=1e-6)
    assert result["held_out_sky_within_1deg_of_training_sky"] == 1.0
    fits = result["direct_fit_mae_on_training_sky"]
    assert set(fits) == {"degree1", "degree2", "degree3", "degree3_grid16"}
    assert fits["degree1"] < 0.01  # the family holds the truth: the fit finds it
    uniform = SkyModel(degree=0, initial_color=tuple(colours.mean(dim=0).tolist()))
    assert probe.sky_fit(uniform, rays, sky_lr=0.05, steps=1)["run_sky_mae_on_training_sky"] > 0.01
