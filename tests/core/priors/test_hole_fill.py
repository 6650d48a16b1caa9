"""The gradient-domain hole fill: against a dense least-squares solve, and what it is for."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.priors.auto import AutoPriorSettings, fuse_view
from esgs.core.priors.hole_fill import gradient_fill
from esgs.core.priors.io import PriorMaps

H, W = 30, 50


def _plane() -> np.ndarray:
    rows, columns = np.mgrid[0:H, 0:W].astype(np.float32)
    return 5.0 + 0.08 * columns + 0.3 * rows


def _hole() -> np.ndarray:
    hole = np.zeros((H, W), bool)
    hole[8:22, 12:38] = True
    return hole


def _dense_solution(guide, known, region, anchors, anchor_weight, reach):
    """The same least squares written out row by row and solved densely (the reference)."""
    unknown = region & (guide > 0) & ~(known > 0)
    index = -np.ones((H, W), int)
    index[unknown] = np.arange(unknown.sum())
    g = np.log(np.where(guide > 0, guide, 1.0))
    rows, rhs = [], []
    for (ya, xa, yb, xb) in [(y, x, y, x + 1) for y in range(H) for x in range(W - 1)] + \
                            [(y, x, y + 1, x) for y in range(H - 1) for x in range(W)]:
        a, b = index[ya, xa], index[yb, xb]
        if (a < 0 and b < 0) or not (guide[ya, xa] > 0 and guide[yb, xb] > 0):
            continue
        if (a < 0 and not known[ya, xa] > 0) or (b < 0 and not known[yb, xb] > 0):
            continue  # a neighbour that is neither unknown nor known
        row = np.zeros(unknown.sum())
        value = g[ya, xa] - g[yb, xb]
        if a >= 0:
            row[a] += 1
        else:
            value -= np.log(known[ya, xa])
        if b >= 0:
            row[b] -= 1
        else:
            value += np.log(known[yb, xb])
        rows.append(row)
        rhs.append(value)
    screen = 1.0 / (reach * max(H, W)) ** 2
    for y, x in zip(*np.nonzero(unknown)):
        row = np.zeros(unknown.sum())
        row[index[y, x]] = np.sqrt(screen)
        rows.append(row)
        rhs.append(np.sqrt(screen) * g[y, x])
        if anchors[y, x] > 0:
            row = np.zeros(unknown.sum())
            row[index[y, x]] = np.sqrt(anchor_weight)
            rows.append(row)
            rhs.append(np.sqrt(anchor_weight) * np.log(anchors[y, x]))
    solution = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    out = np.zeros((H, W))
    out[unknown] = np.exp(solution)
    return out


def test_matches_a_dense_least_squares_solve_with_anchors_screening_and_gaps():
    rng = np.random.default_rng(0)
    guide = (_plane() * np.exp(0.1 * rng.standard_normal((H, W)))).astype(np.float32)
    guide[15, 5:45] = 0.0  # a row with no guide: no terms through it
    region = _hole() | (rng.random((H, W)) < 0.05)
    known = np.where(region, 0.0, _plane()).astype(np.float32)
    known[0:3, :] = 0.0  # pixels neither known nor to fill
    anchors = np.zeros((H, W), np.float32)
    anchors[10:20:4, 15:35:5] = 9.0
    filled = gradient_fill(guide, known, region, anchors=anchors, anchor_weight=0.7, reach=0.3,
                           border_tolerance=None, tolerance=1e-12)
    reference = _dense_solution(guide, known, region, anchors, 0.7, 0.3)
    np.testing.assert_allclose(filled, reference, rtol=1e-4, atol=1e-6)
    assert (filled[~region] == 0).all() and (filled[guide <= 0] == 0).all()


def test_the_coarse_start_of_a_large_problem_leads_to_the_same_fill(monkeypatch):
    """Above COARSE_ABOVE pixels CG starts from the problem solved at half resolution (twice
    here, recursively); the answer is the problem's, not the start's."""
    import esgs.core.priors.hole_fill as hole_fill

    rng = np.random.default_rng(1)
    guide = (_plane() * np.exp(0.3 * np.mgrid[0:H, 0:W][1] / W + 0.02 * rng.standard_normal((H, W)))).astype(np.float32)
    region = _hole()
    region[2:6, 3:9] = True  # a second hole
    known = np.where(region, 0.0, _plane()).astype(np.float32)
    known[8:22, 11] *= 0.4  # a sliver the border check drops
    anchors = np.zeros((H, W), np.float32)
    anchors[10:20:4, 15:35:5] = _plane()[10:20:4, 15:35:5]
    reference = _dense_solution(guide, np.where((np.arange(W) == 11)[None] & (np.arange(H)[:, None] >= 8)
                                                & (np.arange(H)[:, None] < 22), 0.0, known), region, anchors, 1.0, 1.0)
    monkeypatch.setattr(hole_fill, "COARSE_ABOVE", 50)
    cascaded = gradient_fill(guide, known, region, anchors=anchors, tolerance=1e-10)
    np.testing.assert_allclose(cascaded, reference, rtol=1e-5, atol=1e-6)
    # and the start is the point: after three iterations it is far nearer the answer
    early = {}
    for above in (50, 10**9):
        monkeypatch.setattr(hole_fill, "COARSE_ABOVE", above)
        fill = gradient_fill(guide, known, region, anchors=anchors, max_iterations=3)
        early[above] = float(np.abs(np.log(fill[region] / reference[region])).mean())
    assert early[50] < 0.5 * early[10**9], early


def test_a_guide_with_the_right_shape_at_the_wrong_level_is_levelled_by_the_border():
    truth = _plane()
    hole = _hole()
    filled = gradient_fill(truth * 1.4, np.where(hole, 0.0, truth), hole, reach=100.0, tolerance=1e-10)
    np.testing.assert_allclose(filled[hole], truth[hole], rtol=1e-3)
    # a short reach leaves the hole's middle nearer the guide's level than its border
    short = gradient_fill(truth * 1.4, np.where(hole, 0.0, truth), hole, reach=0.05, tolerance=1e-10)
    ratio = short / np.where(hole, truth, 1.0)
    assert ratio[15, 25] > ratio[8, 25] + 0.05 and ratio[8, 25] < 1.15


def test_a_hole_that_touches_nothing_known_keeps_the_guide_and_anchors_pull_it():
    truth = _plane()
    hole = _hole()
    filled = gradient_fill(truth * 1.4, np.zeros((H, W), np.float32), hole)
    np.testing.assert_allclose(filled[hole], 1.4 * truth[hole], rtol=1e-5)
    anchors = np.where(hole, truth, 0.0).astype(np.float32)  # every hole pixel measured
    pulled = gradient_fill(truth * 1.4, np.zeros((H, W), np.float32), hole, anchors=anchors, anchor_weight=1.0)
    np.testing.assert_allclose(pulled[hole], truth[hole], rtol=5e-3)  # the screening keeps a trace of the guide


def test_border_labels_that_disagree_with_the_rest_of_their_hole_border_are_not_used():
    """A sliver of wrong labels (60 % too near) along part of a hole's border: with the
    tolerance the hole is levelled by the rest of its border; with every border label it is
    dragged towards the sliver."""
    truth = _plane()
    hole = _hole()
    known = np.where(hole, 0.0, truth).astype(np.float32)
    known[8:22, 11] *= 0.4  # the column just left of the hole
    guide = truth * 1.2
    kept = gradient_fill(guide, known, hole, reach=100.0, tolerance=1e-10)
    every = gradient_fill(guide, known, hole, reach=100.0, border_tolerance=None, tolerance=1e-10)
    error = {name: float(np.mean(np.abs(fill[hole] - truth[hole]) / truth[hole])) for name, fill in
             (("kept", kept), ("every", every))}
    assert error["kept"] < 1e-3 < 0.05 < error["every"], error


def test_a_border_whose_level_drifts_is_checked_against_a_plane_not_its_median():
    """NDN's level off by a factor that drifts across a long hole (as on rover views): a check
    against the border's median drops the good labels at both ends, the robust plane keeps them
    and still drops a sliver of wrong labels."""
    truth = _plane()
    hole = np.zeros((H, W), bool)
    hole[8:22, 3:47] = True
    columns = np.mgrid[0:H, 0:W][1]
    guide = truth * np.exp(-1.2 * columns / W)
    known = np.where(hole, 0.0, truth).astype(np.float32)
    known[7, 20:26] *= 0.5  # a sliver on the upper border
    fills = {fit: gradient_fill(guide, known, hole, reach=100.0, border_fit=fit, tolerance=1e-10)
             for fit in ("median", "plane")}
    error = {fit: float(np.mean(np.abs(fill[hole] - truth[hole]) / truth[hole])) for fit, fill in fills.items()}
    assert error["plane"] < 2e-3 and error["median"] > 5 * error["plane"], error


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="reach"):
        gradient_fill(_plane(), _plane(), _hole(), reach=0.0)
    with pytest.raises(ValueError, match="border_fit"):
        gradient_fill(_plane(), _plane(), _hole(), border_fit="spline")
    with pytest.raises(ValueError, match="shape"):
        gradient_fill(_plane(), _plane()[:, :10], _hole())


def _maps(depth, mask=None, relative=False):
    mask = np.ones(depth.shape, bool) if mask is None else mask
    return PriorMaps(depth=depth.astype(np.float32), normal=np.zeros((*depth.shape, 3), np.float32), mask=mask,
                     relative_depth=relative)


def test_auto_fills_a_hole_level_with_the_labels_where_ndn_drifts():
    """NDN continuous but tilted (its depth 60 % too far at one side of the image relative to the
    other, as monocular depth drifts): pinned to the points with one scale and shift it stays off
    in the hole; the gradient fill meets the labels and removes most of the error (a tilt in log
    depth is harmonic: with an unlimited reach it would vanish)."""
    truth = _plane()
    hole = _hole()
    columns = np.mgrid[0:H, 0:W][1]
    ndn = _maps(truth * np.exp(0.5 * columns / W), relative=True)
    labels = _maps(np.where(hole, 0.0, truth), ~hole)
    sfm = np.zeros((H, W), np.float32)
    sfm[::3, ::3] = truth[::3, ::3]
    errors = {}
    for fill in ("pinned", "gradient"):
        fused = fuse_view(sfm, labels, ndn, None, AutoPriorSettings(hole_fill=fill))
        np.testing.assert_array_equal(fused.depth[~hole], truth[~hole])  # labels untouched
        assert fused.mask.all()
        errors[fill] = float(np.mean(np.abs(fused.depth[hole] - truth[hole]) / truth[hole]))
    assert errors["gradient"] < 0.3 * errors["pinned"], errors
    with pytest.raises(Exception, match="hole_fill"):
        AutoPriorSettings(hole_fill="poisson").validate()


def test_auto_keeps_pinned_ndn_where_the_points_in_the_holes_prefer_it():
    """Labels around a hole 10 % too far (all alike, so the border check keeps them), NDN right:
    the gradient fill would carry the labels' error into the hole; the SfM points inside it
    judge the two fills (the gradient one made without them) and pinned NDN stays."""
    from scipy.ndimage import binary_dilation

    truth = _plane()
    hole = _hole()
    ring = binary_dilation(hole, iterations=3) & ~hole
    labels = _maps(np.where(hole, 0.0, np.where(ring, 1.1 * truth, truth)), ~hole)
    ndn = _maps(0.5 * truth + 2.0, relative=True)  # affine in the truth: pinned exactly
    sfm = np.zeros((H, W), np.float32)
    sfm[::2, ::2] = truth[::2, ::2]
    checked = fuse_view(sfm, labels, ndn, None, AutoPriorSettings())
    np.testing.assert_allclose(checked.depth[hole], truth[hole], rtol=1e-4)
    assert checked.report["fill"]["used"] == "pinned"
    assert checked.report["fill"]["pinned_error"] < 1e-4 < 0.05 < checked.report["fill"]["gradient_error"]
    unchecked = fuse_view(sfm, labels, ndn, None, AutoPriorSettings(fill_check=False))
    assert unchecked.report["fill"]["used"] == "gradient"
    assert np.mean(np.abs(unchecked.depth[hole] - truth[hole]) / truth[hole]) > 0.03
