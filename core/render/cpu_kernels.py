"""Numba kernels of the CPU backend: tile binning, alpha compositing and its backward.

Layout: the visible Gaussians are first packed in depth order (rank 0 = nearest) for
binning. The compositing kernels then read one row per tile-Gaussian pair, gathered in
tile order: ``splats [P, 8]`` (mean x, mean y, conic a, b, c, opacity, level, unused),
``boxes [P, 4]`` inclusive pixel bounds (x0, x1, y0, y1) and ``features [P, F]``. A tile
streams through consecutive rows instead of jumping through memory (with 100k+
Gaussians the per-Gaussian arrays do not fit in cache, and a cache miss per pair cost
more than the pixels). Images are [H, W, F]. The same kernels serve
float32 and float64 inputs (Numba compiles one version per dtype and caches both); all
arithmetic constants come in through ``constants`` so float32 data stays in float32.

Compositing walks each tile's depth-sorted Gaussian list, and for each Gaussian only the
pixels of the tile inside its ellipse (row by row, from the quadratic's roots). Per pixel
the order is still front to back, so the result equals a per-pixel walk. A Gaussian is
skipped at a pixel without an ``exp`` when its Mahalanobis distance exceeds the level at
which its alpha falls below 1/255.

Determinism: tiles write only their own pixels and their own gradient records (one per
tile-Gaussian pair); per-Gaussian gradients are then summed pair by pair in a fixed order.
Nothing depends on thread scheduling, so outputs and gradients are bit-identical between
runs and thread counts.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# Indices into the ``constants`` array (same dtype as the data).
C_HALF, C_ONE, C_TWO, C_ALPHA_MIN, C_ALPHA_MAX, C_T_MIN, C_SLACK = range(7)
#: Per-pair gradient record columns before the feature gradients.
R_MEAN_X, R_MEAN_Y, R_CONIC_A, R_CONIC_B, R_CONIC_C, R_OPACITY = range(6)
RECORD_FIXED = 6


S_MEAN_X, S_MEAN_Y, S_CONIC_A, S_CONIC_B, S_CONIC_C, S_OPACITY, S_LEVEL = range(7)
SPLAT_COLUMNS = 8


@njit(cache=True, parallel=True)
def prepare_splats(means2d, conics, opacities, cov_diagonal, valid, width, height, log_inv_alpha_min,
                   slack_relative, slack_absolute, alpha_min, keep, level, exact_level, boxes):
    """Cull and bound every Gaussian of one camera (float64 arithmetic).

    means2d [N, 2], conics [N, 3], opacities [N], cov_diagonal [N, 2] (dilated covariance
    diagonal), valid [N] (in front of the camera, invertible). Writes keep [N] (visible),
    exact_level [N] = 2 (log opacity + log 255) (the Mahalanobis level of alpha = 1/255),
    level [N] = that level widened a little for the exp-free skip test, and boxes [N, 4]
    the inclusive pixel bounds of the level ellipse clipped to the image.
    """
    for g in prange(means2d.shape[0]):
        keep[g] = False
        level[g] = 0.0
        exact_level[g] = 0.0
        boxes[g, 0] = 0
        boxes[g, 1] = -1
        boxes[g, 2] = 0
        boxes[g, 3] = -1
        opacity = np.float64(opacities[g])
        if not valid[g] or not opacity >= alpha_min:
            continue
        exact = 2.0 * (math.log(opacity) + log_inv_alpha_min)
        widened = exact * (1.0 + slack_relative) + slack_absolute
        half_x = math.sqrt(widened * np.float64(cov_diagonal[g, 0]))
        half_y = math.sqrt(widened * np.float64(cov_diagonal[g, 1]))
        mx = np.float64(means2d[g, 0])
        my = np.float64(means2d[g, 1])
        if not (math.isfinite(half_x) and math.isfinite(half_y) and math.isfinite(mx) and math.isfinite(my)):
            continue
        # Pixel j is inside when |j + 1/2 - mean| <= half; clip to the image before int casts.
        low_x = min(max(np.ceil(mx - half_x - 0.5), -1.0), np.float64(width))
        high_x = min(max(np.floor(mx + half_x - 0.5), -1.0), np.float64(width))
        low_y = min(max(np.ceil(my - half_y - 0.5), -1.0), np.float64(height))
        high_y = min(max(np.floor(my + half_y - 0.5), -1.0), np.float64(height))
        if high_x < 0 or low_x > width - 1 or high_y < 0 or low_y > height - 1 or low_x > high_x or low_y > high_y:
            continue
        keep[g] = True
        exact_level[g] = exact
        level[g] = widened
        boxes[g, 0] = max(int(low_x), 0)
        boxes[g, 1] = min(int(high_x), width - 1)
        boxes[g, 2] = max(int(low_y), 0)
        boxes[g, 3] = min(int(high_y), height - 1)


@njit(cache=True, parallel=True)
def pack_splats(order, means2d, conics, opacities, level, boxes, splats, packed_boxes):
    """Gather the visible Gaussians into depth order: splats [M, 8], packed_boxes [M, 4]."""
    for i in prange(order.shape[0]):
        g = order[i]
        splats[i, S_MEAN_X] = means2d[g, 0]
        splats[i, S_MEAN_Y] = means2d[g, 1]
        splats[i, S_CONIC_A] = conics[g, 0]
        splats[i, S_CONIC_B] = conics[g, 1]
        splats[i, S_CONIC_C] = conics[g, 2]
        splats[i, S_OPACITY] = opacities[g]
        splats[i, S_LEVEL] = level[g]
        splats[i, 7] = 0
        for j in range(4):
            packed_boxes[i, j] = boxes[g, j]


@njit(cache=True, parallel=True)
def gather_rows(index, source, out):
    """out[k] = source[index[k]] for 2D arrays (rows gathered in parallel)."""
    for k in prange(index.shape[0]):
        row = index[k]
        for j in range(source.shape[1]):
            out[k, j] = source[row, j]


@njit(cache=True)
def bin_gaussians(boxes, tile_size, tiles_x, tiles_y):
    """Tile lists by counting sort over the depth-ordered Gaussians.

    boxes: [M, 4] inclusive pixel bounds in depth order. Returns tile_start [T + 1],
    pair_rank [P] (per tile, front to back), rank_pair_start [M + 1] and rank_pairs [P]
    (the pair positions of each rank, for the gradient reduction).
    """
    tiles = tiles_x * tiles_y
    count = boxes.shape[0]
    counts = np.zeros(tiles + 1, dtype=np.int64)
    rank_pair_start = np.zeros(count + 1, dtype=np.int64)
    for i in range(count):
        tx0 = boxes[i, 0] // tile_size
        tx1 = boxes[i, 1] // tile_size
        ty0 = boxes[i, 2] // tile_size
        ty1 = boxes[i, 3] // tile_size
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                counts[ty * tiles_x + tx + 1] += 1
        rank_pair_start[i + 1] = rank_pair_start[i] + (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
    tile_start = np.cumsum(counts)
    pairs = tile_start[tiles]
    cursor = tile_start[:tiles].copy()
    pair_rank = np.empty(pairs, dtype=np.int32)
    rank_pairs = np.empty(pairs, dtype=np.int64)
    for i in range(count):
        tx0 = boxes[i, 0] // tile_size
        tx1 = boxes[i, 1] // tile_size
        ty0 = boxes[i, 2] // tile_size
        ty1 = boxes[i, 3] // tile_size
        slot = rank_pair_start[i]
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                tile = ty * tiles_x + tx
                position = cursor[tile]
                cursor[tile] = position + 1
                pair_rank[position] = i
                rank_pairs[slot] = position
                slot += 1
    return tile_start, pair_rank, rank_pair_start, rank_pairs


@njit(cache=True, inline="always")
def _row_span(dy, b, inverse_a, a_level, conic_det, mean_x, x_first, x_stop, half, slack):
    """Pixels [start, stop) of one row, clipped to [x_first, x_stop), whose centre x + 1/2
    satisfies a dx^2 + 2 b dx dy + c dy^2 <= level (a little wider, never narrower).

    The roots are dx = (-b dy +- sqrt(a level - (a c - b^2) dy^2)) / a; the caller passes
    1 / a, a level and a c - b^2, which are per Gaussian.
    """
    disc = a_level - conic_det * dy * dy
    if disc < 0:
        return 0, 0
    root = math.sqrt(disc)
    centre = mean_x - b * dy * inverse_a - half
    reach = root * inverse_a + slack
    low = centre - reach
    high = centre + reach
    if low < x_first:
        low = x_first
    if high > x_stop:
        high = x_stop
    start = int(math.ceil(low))
    stop = int(math.floor(high)) + 1
    if start < x_first:
        start = x_first
    if stop > x_stop:
        stop = x_stop
    return start, stop


@njit(cache=True, inline="always")
def _tile_bounds(tile, tiles_x, tile_size, width, height):
    """Pixels [x0, x1) x [y0, y1) of tile number ``tile`` (row-major), clipped to the image."""
    tile_y = tile // tiles_x
    tile_x = tile - tile_y * tiles_x
    x0 = tile_x * tile_size
    y0 = tile_y * tile_size
    return x0, y0, min(x0 + tile_size, width), min(y0 + tile_size, height)


@njit(cache=True, inline="always")
def _footprint(boxes, g, x0, y0, x1, y1):
    """Rows [row_first, row_stop) and columns [col_first, col_stop) of pair ``g``'s box inside
    the tile [x0, x1) x [y0, y1) (empty ranges when they do not meet)."""
    return max(boxes[g, 2], y0), min(boxes[g, 3] + 1, y1), max(boxes[g, 0], x0), min(boxes[g, 1] + 1, x1)


@njit(cache=True, inline="always")
def _splat(splats, g, one):
    """Pair ``g``'s mean x, y, conic a, b, c, opacity and level, then what :func:`_row_span`
    needs per Gaussian: 1 / a, a level and a c - b^2."""
    a = splats[g, S_CONIC_A]
    b = splats[g, S_CONIC_B]
    c = splats[g, S_CONIC_C]
    q_max = splats[g, S_LEVEL]
    return (splats[g, S_MEAN_X], splats[g, S_MEAN_Y], a, b, c, splats[g, S_OPACITY], q_max,
            one / a, a * q_max, a * c - b * b)


@njit(cache=True, parallel=True)
def composite_forward(tile_order, tile_start, tiles_x, tile_size, centres_x, centres_y,
                      splats, boxes, features, constants,
                      out_features, out_transmittance, out_stop, out_crossing, tile_evaluations):
    """Front-to-back compositing of every tile.

    out_features [H, W, F] receives sum w f; out_transmittance [H, W] the final T;
    out_stop [H, W] the pair position at which the pixel stopped (its tile's end if it
    never did); out_crossing [H, W] the pair position of the Gaussian that took the
    transmittance from above one half to one half or below (the pixel's median surface;
    -1 where T stays above a half); tile_evaluations [T] the Gaussian-pixel evaluations per
    tile. Each tile works in small local buffers (one flat index per pixel) and writes back
    at the end.
    """
    half = constants[C_HALF]
    one = constants[C_ONE]
    two = constants[C_TWO]
    alpha_min = constants[C_ALPHA_MIN]
    alpha_max = constants[C_ALPHA_MAX]
    t_min = constants[C_T_MIN]
    slack = constants[C_SLACK]
    height, width, channels = out_features.shape
    tile_pixels = tile_size * tile_size
    for i in prange(tile_order.shape[0]):
        tile = tile_order[i]
        x0, y0, x1, y1 = _tile_bounds(tile, tiles_x, tile_size, width, height)
        start = tile_start[tile]
        end = tile_start[tile + 1]
        transmittance = np.ones(tile_pixels, dtype=features.dtype)
        stop = np.full(tile_pixels, end, dtype=np.int64)
        crossing = np.full(tile_pixels, -1, dtype=np.int64)
        accumulated = np.zeros((tile_pixels, channels), dtype=features.dtype)
        active = (x1 - x0) * (y1 - y0)
        evaluations = 0
        for k in range(start, end):
            g = k
            row_first, row_stop, col_first, col_stop = _footprint(boxes, g, x0, y0, x1, y1)
            mx, my, a, b, c, o, q_max, inverse_a, a_level, conic_det = _splat(splats, g, one)
            for y in range(row_first, row_stop):
                dy = centres_y[y] - my
                xa, xb = _row_span(dy, b, inverse_a, a_level, conic_det, mx, col_first, col_stop, half, slack)
                cross = two * b * dy
                row_term = c * dy * dy
                base = (y - y0) * tile_size - x0
                for x in range(xa, xb):
                    p = base + x
                    if stop[p] != end:
                        continue
                    dx = centres_x[x] - mx
                    q = (a * dx + cross) * dx + row_term
                    evaluations += 1
                    if q > q_max:
                        continue
                    alpha = o * math.exp(-half * q)
                    if alpha > alpha_max:
                        alpha = alpha_max
                    if alpha < alpha_min:
                        continue
                    before = transmittance[p]
                    after = before * (one - alpha)
                    if after < t_min:
                        stop[p] = k
                        active -= 1
                        continue
                    weight = alpha * before
                    for ch in range(channels):
                        accumulated[p, ch] += weight * features[g, ch]
                    transmittance[p] = after
                    if after <= half < before:
                        crossing[p] = k
            if active == 0:
                break
        for y in range(y0, y1):
            for x in range(x0, x1):
                p = (y - y0) * tile_size + (x - x0)
                out_transmittance[y, x] = transmittance[p]
                out_stop[y, x] = stop[p]
                out_crossing[y, x] = crossing[p]
                for ch in range(channels):
                    out_features[y, x, ch] = accumulated[p, ch]
        tile_evaluations[tile] = evaluations


@njit(cache=True, parallel=True)
def composite_backward(tile_order, tile_start, tiles_x, tile_size, centres_x, centres_y,
                       splats, boxes, features, constants,
                       final_transmittance, final_stop, grad_features, grad_alpha, records):
    """Per-pair gradient records, walking each tile's Gaussians back to front.

    grad_features [H, W, F], grad_alpha [H, W]: gradients of the composited features and of
    alpha = 1 - final T. records [P, 6 + F] receives, per pair, the gradients w.r.t. mean x,
    mean y, conic a, b, c, opacity and the F features (summed over the tile's pixels).
    """
    half = constants[C_HALF]
    one = constants[C_ONE]
    two = constants[C_TWO]
    alpha_min = constants[C_ALPHA_MIN]
    alpha_max = constants[C_ALPHA_MAX]
    slack = constants[C_SLACK]
    zero = one - one
    height, width, channels = grad_features.shape
    tile_pixels = tile_size * tile_size
    for i in prange(tile_order.shape[0]):
        tile = tile_order[i]
        x0, y0, x1, y1 = _tile_bounds(tile, tiles_x, tile_size, width, height)
        start = tile_start[tile]
        end = tile_start[tile + 1]
        if end == start:
            continue
        # Local copies: T after the current Gaussian, the upstream-weighted sum of the
        # features behind it (sum_c dL/dF_c sum_j>i w_j f_jc: one number per pixel instead of
        # F), and the per-pixel inputs, all with one flat index per pixel.
        transmittance = np.zeros(tile_pixels, dtype=features.dtype)
        alpha_term = np.zeros(tile_pixels, dtype=features.dtype)
        stop = np.zeros(tile_pixels, dtype=np.int64)
        behind = np.zeros(tile_pixels, dtype=features.dtype)
        upstream = np.zeros((tile_pixels, channels), dtype=features.dtype)
        for y in range(y0, y1):
            for x in range(x0, x1):
                p = (y - y0) * tile_size + (x - x0)
                transmittance[p] = final_transmittance[y, x]
                # d alpha_out / d alpha_i = T_final / (1 - alpha_i): keep the numerator.
                alpha_term[p] = grad_alpha[y, x] * final_transmittance[y, x]
                stop[p] = final_stop[y, x]
                for ch in range(channels):
                    upstream[p, ch] = grad_features[y, x, ch]
        grad_feature_sum = np.zeros(channels, dtype=features.dtype)
        for k in range(end - 1, start - 1, -1):
            g = k
            row_first, row_stop, col_first, col_stop = _footprint(boxes, g, x0, y0, x1, y1)
            mx, my, a, b, c, o, q_max, inverse_a, a_level, conic_det = _splat(splats, g, one)
            g_mx = zero
            g_my = zero
            g_a = zero
            g_b = zero
            g_c = zero
            g_o = zero
            for ch in range(channels):
                grad_feature_sum[ch] = zero
            for y in range(row_first, row_stop):
                dy = centres_y[y] - my
                xa, xb = _row_span(dy, b, inverse_a, a_level, conic_det, mx, col_first, col_stop, half, slack)
                cross = two * b * dy
                row_term = c * dy * dy
                base = (y - y0) * tile_size - x0
                for x in range(xa, xb):
                    p = base + x
                    if k >= stop[p]:
                        continue
                    dx = centres_x[x] - mx
                    q = (a * dx + cross) * dx + row_term
                    if q > q_max:
                        continue
                    gaussian = math.exp(-half * q)
                    raw = o * gaussian
                    alpha = raw
                    if alpha > alpha_max:
                        alpha = alpha_max
                    if alpha < alpha_min:
                        continue
                    inv_keep = one / (one - alpha)
                    before = transmittance[p] * inv_keep
                    weight = alpha * before
                    # dL/dalpha_i = sum_c up_c (T_i f_ic - S_c / (1 - alpha_i)) + dL/dalpha_out T_final / (1 - alpha_i)
                    dot = zero
                    for ch in range(channels):
                        up = upstream[p, ch]
                        dot += up * features[g, ch]
                        grad_feature_sum[ch] += weight * up
                    grad_alpha_here = before * dot + (alpha_term[p] - behind[p]) * inv_keep
                    behind[p] += weight * dot
                    transmittance[p] = before
                    if raw <= alpha_max:
                        g_o += gaussian * grad_alpha_here
                        grad_q = -half * raw * grad_alpha_here
                        g_a += grad_q * dx * dx
                        g_b += grad_q * two * dx * dy
                        g_c += grad_q * dy * dy
                        g_mx -= grad_q * two * (a * dx + b * dy)
                        g_my -= grad_q * two * (b * dx + c * dy)
            records[k, R_MEAN_X] = g_mx
            records[k, R_MEAN_Y] = g_my
            records[k, R_CONIC_A] = g_a
            records[k, R_CONIC_B] = g_b
            records[k, R_CONIC_C] = g_c
            records[k, R_OPACITY] = g_o
            for ch in range(channels):
                records[k, RECORD_FIXED + ch] = grad_feature_sum[ch]


@njit(cache=True, parallel=True)
def reduce_records(order, rank_pair_start, rank_pairs, records, out):
    """out[order[i]] = sum of the records of rank i's pairs, always in the same order.

    out: [N, 6 + F], zero on entry.
    """
    columns = records.shape[1]
    for i in prange(order.shape[0]):
        g = order[i]
        for r in range(rank_pair_start[i], rank_pair_start[i + 1]):
            position = rank_pairs[r]
            for j in range(columns):
                out[g, j] += records[position, j]
