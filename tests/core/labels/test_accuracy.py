"""AbsRel / delta1 of labels against ground truth, on maps with known errors."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.errors import DatasetError
from esgs.core.formats.imageio import write_png
from esgs.core.labels.accuracy import depth_errors, format_accuracy_table, label_accuracy
from esgs.core.priors.io import write_prior_maps


def test_depth_errors_by_hand():
    truth = np.array([1.0, 2.0, 4.0, 10.0])
    label = np.array([1.1, 2.0, 3.0, 14.0])
    errors = depth_errors(label, truth)
    assert errors["abs_rel"] == pytest.approx((0.1 + 0 + 0.25 + 0.4) / 4)
    assert errors["delta1"] == pytest.approx(2 / 4)  # 1.1 and 1.0 pass; 4/3 and 1.4 fail
    assert errors["pixels"] == 4


def test_label_accuracy_pools_views_and_separates_filled_pixels(tmp_path):
    truth = np.full((10, 10), 4.0, np.float32)
    truth[:2] = 0.0  # sky in the truth
    label = np.full((10, 10), 4.4, np.float32)  # 10 % too far where rendered
    label[5:7, 5:7] = 4.0  # filled pixels, exact
    label[:2] = 0.0
    label[9] = 0.0  # no label on the last row (coverage 70 of 80)
    mask = np.where(label > 0, 255, 0).astype(np.uint8)
    mask[5:7, 5:7] = 128
    write_prior_maps(tmp_path, "gt", "a.png", depth=truth, mask=truth > 0)
    write_prior_maps(tmp_path, "labels", "a.png", depth=label)
    write_png(tmp_path / "priors" / "labels" / "mask" / "a.png", mask)
    report = label_accuracy(tmp_path)
    assert report["overall"]["pixels"] == 70
    assert report["overall"]["abs_rel"] == pytest.approx(66 * 0.1 / 70, rel=1e-5)
    assert report["filled"]["abs_rel"] == pytest.approx(0.0, abs=1e-7) and report["filled"]["pixels"] == 4
    assert report["rendered"]["abs_rel"] == pytest.approx(0.1, rel=1e-5)
    assert report["coverage"] == pytest.approx(70 / 80)
    assert report["baseline_median_depth"]["abs_rel"] == pytest.approx(0.0)  # flat truth: the median is exact
    assert sum(row["pixels"] for row in report["by_depth"]) >= 70  # every compared pixel lies in a range bin
    assert "AbsRel" in format_accuracy_table(report) and "depth 4-4" in format_accuracy_table(report)


def test_missing_ground_truth_is_a_clear_error(tmp_path):
    with pytest.raises(DatasetError, match="no depth maps"):
        label_accuracy(tmp_path)
