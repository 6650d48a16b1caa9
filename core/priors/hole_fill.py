"""Filling the holes of a metric depth map with the shape of a dense guide (gradient-domain fill).

``priors/auto`` takes stereo labels where multi-view stereo held and a dense network prediction
elsewhere. Pinned to the SfM points with one scale and shift per view, the network's depth is
right on average but not where it meets the labels: a hole's fill sits a few percent (on rover
views tens of percent) nearer or farther than the labelled ground around it. This module keeps
the guide's *shape* (the differences of log depth between neighbouring pixels) and takes its
*level* from the labels at the hole's border: a screened Poisson problem in log depth, the
technique of gradient-domain image blending applied to depth.

For the unknown log depths ``x`` of the hole pixels, least squares over

- every 4-neighbour pair ``(p, q)`` with at least one unknown and both guided:
  ``x_p - x_q = g_p - g_q`` (``g`` = log guide; a known neighbour enters with its value);
- every unknown: ``sqrt(screen) * (x_p - g_p) = 0``, which keeps a hole that touches no label at
  the guide and makes the border's correction fade over ``reach`` of the image's longer side
  (``screen = 1 / (reach * side)^2``);
- optional metric anchors inside holes (SfM points): ``sqrt(anchor_weight) * (x_p - log a_p) = 0``.

Before that, each hole's border labels are checked against one another: a label whose level
(log of known over guide) is farther than ``border_tolerance`` from a plane of level over the
image fitted robustly to the hole's border (or from the border's median) is left out, since a
sliver of rebuilt mesh draped over a depth edge would otherwise drag the whole hole.

Log depth makes the fit relative (a 1 m step at 5 m weighs what a 10 m step at 50 m does) and
keeps every filled depth positive. The normal equations are a sparse symmetric positive definite
system, solved by conjugate gradients from the guide (each hole is independent; far from a
border the answer is the guide, so few iterations are needed).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

#: Default reach of a border's correction, as a share of the image's longer side.
DEFAULT_REACH = 1.0
#: Default largest departure (log depth) of a border pixel's level from what its hole's border predicts.
DEFAULT_BORDER_TOLERANCE = 0.4
#: What a hole's border labels are checked against: their median level, or a robust plane of
#: level over the image (a rover view's border drifts in level along a long hole).
BORDER_FITS = ("plane", "median")
#: With more pixels to fill than this, CG starts from the same problem solved at half resolution
#: (recursively): the correction is smooth, and CG alone needs thousands of iterations to carry
#: it across a hole of a million pixels.
COARSE_ABOVE = 40_000


def _half(values: np.ndarray, fill: float | bool) -> np.ndarray:
    """``values`` [H, W] padded to even sides with ``fill`` and cut into 2x2 blocks [H/2, 2, W/2, 2]."""
    height, width = values.shape
    padded = np.pad(values, ((0, height % 2), (0, width % 2)), constant_values=fill)
    return padded.reshape(padded.shape[0] // 2, 2, padded.shape[1] // 2, 2)


def _coarse_start(unknown: np.ndarray, border: np.ndarray, border_count: np.ndarray, anchor: np.ndarray,
                  anchor_count: np.ndarray, anchor_weight: float, reach: float) -> np.ndarray:
    """The level offset (fill minus guide, log depth) [H, W] from the problem at half resolution.

    In offsets the problem is a screened membrane: no guide, the border's offsets held (here at
    the unknown pixels next to the border: ``border`` sums and ``border_count`` counts them per
    pixel), anchors' offsets pulled (``anchor``, ``anchor_count``). A 2x2 block holding border
    pixels is held at their mean; one holding only unknowns is solved (by :func:`gradient_fill`
    with a flat guide, so it recurses while the problem is large)."""
    held = _half(border_count, 0).sum(axis=(1, 3))
    level = np.where(held > 0, _half(border, 0.0).sum(axis=(1, 3)) / np.maximum(held, 1), 0.0)
    region = _half(unknown, False).any(axis=(1, 3)) & (held == 0)
    pulled = _half(anchor_count, 0).sum(axis=(1, 3))
    anchors = np.where(pulled > 0, np.exp(_half(anchor, 0.0).sum(axis=(1, 3)) / np.maximum(pulled, 1)), 0.0)
    solved = gradient_fill(np.ones(region.shape), np.where(held > 0, np.exp(level), 0.0), region, anchors=anchors,
                           anchor_weight=anchor_weight, reach=reach, border_tolerance=None, tolerance=1e-3)
    offset = np.where(region, np.log(np.where(solved > 0, solved, 1.0)), level)
    height, width = unknown.shape
    return np.repeat(np.repeat(offset, 2, axis=0), 2, axis=1)[:height, :width]


def _border_levels(component_of: np.ndarray, at: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Per hole (component number, 0 unused): the median level offset (known over guide, log) of
    its border edges ``at`` (unknown indices) with offsets ``offset``; 0 for a hole with none."""
    from scipy import ndimage

    levels = np.zeros(int(component_of.max(initial=0)) + 1)
    if len(at):
        edge_component = component_of[at]
        names = np.unique(edge_component)
        levels[names] = np.asarray(ndimage.median(offset, labels=edge_component, index=names), dtype=np.float64)
    return levels


def _robust_planes(component: np.ndarray, rows: np.ndarray, cols: np.ndarray, offset: np.ndarray,
                   start: np.ndarray, limit: float, rounds: int = 3, min_edges: int = 12) -> np.ndarray:
    """Per border edge, the level its hole's border predicts there: a plane in image position
    fitted per hole to the edges within ``limit`` of the current prediction (``start``: the
    median), refitted ``rounds`` times; a hole with fewer than ``min_edges`` such edges keeps
    ``start``."""
    expected = start.copy()
    count = int(component.max(initial=0)) + 1
    for _ in range(rounds):
        inside = np.abs(offset - expected) <= limit
        basis = np.stack([np.ones_like(rows), rows, cols], axis=1)[inside]
        names = component[inside]
        gram = np.zeros((count, 3, 3))
        moment = np.zeros((count, 3))
        for i in range(3):
            moment[:, i] = np.bincount(names, basis[:, i] * offset[inside], minlength=count)
            for j in range(3):
                gram[:, i, j] = np.bincount(names, basis[:, i] * basis[:, j], minlength=count)
        enough = (gram[:, 0, 0] >= min_edges) & (np.abs(np.linalg.det(gram)) > 1e-12)
        coefficients = np.zeros((count, 3))
        if enough.any():
            coefficients[enough] = np.linalg.solve(gram[enough], moment[enough][..., None])[..., 0]
        fitted = enough[component]
        plane = coefficients[component]
        expected = np.where(fitted, plane[:, 0] + plane[:, 1] * rows + plane[:, 2] * cols, start)
    return expected


def _scatter(unknown: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Per-unknown ``values`` back into an [H, W] map (0 elsewhere)."""
    out = np.zeros(unknown.shape)
    out[unknown] = values
    return out


def gradient_fill(guide: np.ndarray, known: np.ndarray, region: np.ndarray, *,
                  anchors: Optional[np.ndarray] = None, anchor_weight: float = 1.0,
                  reach: float = DEFAULT_REACH, border_tolerance: Optional[float] = DEFAULT_BORDER_TOLERANCE,
                  border_fit: str = "plane",
                  tolerance: float = 1e-5, max_iterations: int = 3000) -> np.ndarray:
    """Depth [H, W] over ``region`` shaped like ``guide`` and level with ``known`` at its border.

    ``guide`` [H, W]: dense depth (> 0 where defined; metric or not: only its log differences
    count, and its level where no border reaches); ``known`` [H, W]: metric depth held fixed
    (> 0 where known); ``region`` [H, W] bool: the pixels to fill (those with a known value or no
    guide are left out of it); ``anchors`` [H, W]: optional metric samples inside the region
    (> 0 where given). ``border_tolerance``: a known border pixel whose level (log of known over
    guide) differs by more than this from what its hole's border predicts there is not used (a
    label on a sliver of rebuilt mesh draped over a depth edge; None = use every border pixel);
    ``border_fit``: the prediction, the border's median level or a plane of level over the image
    fitted robustly to the border (:data:`BORDER_FITS`).
    Returns the filled depth on the region's pixels, 0 elsewhere.
    """
    from scipy import ndimage
    from scipy.sparse import coo_matrix, diags
    from scipy.sparse.linalg import cg

    if reach <= 0:
        raise ValueError(f"reach must be > 0, got {reach}")
    if border_fit not in BORDER_FITS:
        raise ValueError(f"border_fit must be one of {', '.join(BORDER_FITS)}, got {border_fit!r}")
    if guide.shape != known.shape or guide.shape != region.shape:
        raise ValueError(f"guide {guide.shape}, known {known.shape} and region {region.shape} differ in shape")
    height, width = guide.shape
    guided = np.isfinite(guide) & (guide > 0)
    unknown = region & guided & ~(known > 0)
    out = np.zeros((height, width), np.float32)
    count = int(unknown.sum())
    if count == 0:
        return out
    index = np.full((height, width), -1, np.int64)
    index[unknown] = np.arange(count)
    log_guide = np.where(guided, np.log(np.where(guided, guide, 1.0)), 0.0)
    log_known = np.where(known > 0, np.log(np.where(known > 0, known, 1.0)), 0.0)

    # Normal equations assembled directly: each pair term (x_p - x_q - d)^2 adds the graph
    # Laplacian's entries; a known neighbour moves to the right-hand side.
    diagonal = np.zeros(count)
    rhs = np.zeros(count)
    off_rows: list[np.ndarray] = []
    off_cols: list[np.ndarray] = []
    border_index: list[np.ndarray] = []  # per border edge: the unknown pixel and the level it implies
    border_value: list[np.ndarray] = []
    for a_slice, b_slice in (((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                             ((slice(None, -1), slice(None)), (slice(1, None), slice(None)))):
        ia, ib = index[a_slice], index[b_slice]
        ga, gb = guided[a_slice], guided[b_slice]
        ka, kb = (known > 0)[a_slice], (known > 0)[b_slice]
        difference = log_guide[a_slice] - log_guide[b_slice]  # wanted x_a - x_b
        both = (ia >= 0) & (ib >= 0) & ga & gb
        np.add.at(diagonal, ia[both], 1.0)
        np.add.at(diagonal, ib[both], 1.0)
        np.add.at(rhs, ia[both], difference[both])
        np.add.at(rhs, ib[both], -difference[both])
        off_rows += [ia[both], ib[both]]
        off_cols += [ib[both], ia[both]]
        edge = (ia >= 0) & kb & ga & gb  # a unknown, b known: x_a = x_b(known) + difference
        border_index.append(ia[edge])
        border_value.append(log_known[b_slice][edge] + difference[edge])
        edge = (ib >= 0) & ka & ga & gb  # b unknown, a known: x_b = x_a(known) - difference
        border_index.append(ib[edge])
        border_value.append(log_known[a_slice][edge] - difference[edge])
    at = np.concatenate(border_index)
    level = np.concatenate(border_value)
    component_of = ndimage.label(unknown)[0][unknown]  # per unknown index (both number row-major)
    levels = _border_levels(component_of, at, level - log_guide[unknown][at])
    if border_tolerance is not None and len(at):
        # a draped sliver of labels is far from the level the rest of its hole's border gives
        offset = level - log_guide[unknown][at]
        expected = levels[component_of[at]]
        if border_fit == "plane":
            rows_of, cols_of = np.nonzero(unknown)
            side = float(max(height, width))
            expected = _robust_planes(component_of[at], rows_of[at] / side, cols_of[at] / side, offset, expected,
                                      border_tolerance)
        keep = np.abs(offset - expected) <= border_tolerance
        at, level = at[keep], level[keep]
        levels = _border_levels(component_of, at, level - log_guide[unknown][at])
    np.add.at(diagonal, at, 1.0)
    np.add.at(rhs, at, level)
    screen = 1.0 / (reach * max(height, width)) ** 2
    diagonal += screen
    rhs += screen * log_guide[unknown]
    anchored = np.zeros_like(unknown)
    if anchors is not None and anchor_weight > 0:
        anchored = unknown & (anchors > 0)
        diagonal[index[anchored]] += anchor_weight
        rhs[index[anchored]] += anchor_weight * np.log(anchors[anchored])
    rows = np.concatenate(off_rows) if off_rows else np.zeros(0, np.int64)
    cols = np.concatenate(off_cols) if off_cols else np.zeros(0, np.int64)
    matrix = coo_matrix((-np.ones(len(rows)), (rows, cols)), shape=(count, count)).tocsr() + diags(diagonal)
    preconditioner = diags(1.0 / diagonal)
    # started from the guide moved to each hole's border level (or, for a large problem, to the
    # level field solved at half resolution): CG then has little left to carry across the holes
    if count > COARSE_ABOVE:
        border_sum, border_count = np.zeros(count), np.zeros(count)
        np.add.at(border_sum, at, level - log_guide[unknown][at])
        np.add.at(border_count, at, 1.0)
        anchor_sum, anchor_count = np.zeros((height, width)), np.zeros((height, width))
        if anchors is not None and anchor_weight > 0:
            anchor_count[anchored] = 1.0
            anchor_sum[anchored] = np.log(anchors[anchored]) - log_guide[anchored]
        start = log_guide[unknown] + _coarse_start(unknown, _scatter(unknown, border_sum), _scatter(unknown, border_count),
                                                   anchor_sum, anchor_count, anchor_weight, reach)[unknown]
    else:
        start = log_guide[unknown] + levels[component_of]
    solution, _ = cg(matrix, rhs, x0=start, rtol=tolerance, atol=0.0, maxiter=max_iterations,
                     M=preconditioner)
    out[unknown] = np.exp(solution).astype(np.float32)
    return out
