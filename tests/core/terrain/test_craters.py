"""Crater size-frequency distribution: the sampled diameters follow the configured power law."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from esgs.core.terrain import TerrainConfig, generate_terrain
from esgs.core.terrain.craters import fit_sfd_exponent, sample_crater_diameters, sample_craters


def truncated_power_law_cdf(diameters, low, high, exponent):
    return (low ** -exponent - diameters ** -exponent) / (low ** -exponent - high ** -exponent)


@pytest.mark.parametrize("exponent", [1.2, 2.0, 3.0])
def test_maximum_likelihood_exponent_matches(exponent):
    diameters = sample_crater_diameters(4000, 1.0, 50.0, exponent, np.random.default_rng(3))
    assert diameters.min() >= 1.0 and diameters.max() <= 50.0
    # MLE standard error is ~ b / sqrt(n) = 0.05 b: allow three of them.
    assert fit_sfd_exponent(diameters, 1.0, 50.0) == pytest.approx(exponent, rel=0.15)


def test_fit_recovers_exponent_of_independent_samples():
    # Draw by rejection from the density b D^(-b-1) (not by our inverse CDF) to check the fit itself.
    rng = np.random.default_rng(8)
    low, high, exponent = 2.0, 20.0, 1.7
    candidates = rng.uniform(low, high, 400000)
    keep = rng.uniform(0, 1, candidates.size) < (candidates / low) ** (-exponent - 1)
    assert fit_sfd_exponent(candidates[keep], low, high) == pytest.approx(exponent, abs=0.1)


def test_cumulative_counts_follow_the_law():
    low, high, exponent = 1.5, 25.0, 2.0
    diameters = sample_crater_diameters(3000, low, high, exponent, np.random.default_rng(1))
    result = stats.kstest(diameters, lambda d: truncated_power_law_cdf(d, low, high, exponent))
    assert result.pvalue > 0.01
    # N(>D) ratio between two diameters ~ (D1/D2)^-b (away from the truncation at D_max).
    count = lambda d: np.sum(diameters >= d)
    predicted = (3.0 ** -exponent - high ** -exponent) / (1.5 ** -exponent - high ** -exponent)
    assert count(3.0) / count(1.5) == pytest.approx(predicted, rel=0.12)


def test_generated_crater_table_follows_config():
    config = TerrainConfig(resolution=129, extent_m=100.0, crater_count=800, crater_min_diameter_m=2.0,
                           crater_max_diameter_m=40.0, crater_sfd_exponent=2.2, crater_degradation_min=0.2,
                           crater_degradation_max=0.6, sand_fraction=0.0)
    craters = generate_terrain(config, seed=9).craters
    x, y, diameter, depth, degradation = craters.T
    assert craters.shape == (800, 5)
    assert np.abs(x).max() <= 50 and np.abs(y).max() <= 50
    assert fit_sfd_exponent(diameter, 2.0, 40.0) == pytest.approx(2.2, rel=0.15)
    assert degradation.min() >= 0.2 and degradation.max() <= 0.6
    np.testing.assert_allclose(depth, 0.2 * diameter * (1 - 0.8 * degradation))


def test_no_craters_gives_empty_table():
    config = TerrainConfig(resolution=33, crater_count=0)
    assert sample_craters(config, np.random.default_rng(0)).shape == (0, 5)
