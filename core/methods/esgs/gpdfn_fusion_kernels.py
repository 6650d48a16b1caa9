"""Numba kernels of GPDFN's fusion core on the CPU: the fused stack of one Gaussian at a time.

The fusion core (:class:`.gpdfn._FusionCore`) runs, for every fused Gaussian, ``K`` entries
(the Gaussian itself and its ``K - 1`` sampled voxels) through a ReLU, a 16x16 linear layer
and a second ReLU, scores them, and sums them under a softmax of the scores. Written with
torch, that is some thirty passes over ``[K, B, 16]`` blocks and their backward, each a trip to
memory and a small matrix product (profiled at 100k Gaussians: ~60 % of GPDFN's time). Here
each Gaussian's whole stack lives in a few hundred bytes of scratch: the forward writes only
the attention-weighted summary, and the backward recomputes the stack (cheaper than storing
``[K, N, 16]`` activations twice, and ~0.5 KB per fused Gaussian less memory) and
differentiates it in place.

Layout: a chunk's activations are held feature-major, ``[K, H, B]`` for its ``B`` Gaussians, so
every inner loop runs along the chunk's Gaussians (long, contiguous: vectorised), not along the
16 features (too short for the compiler's vector loops).

Determinism: the Gaussians go in fixed chunks of ``chunk`` rows (independent of the thread
count); each chunk sums its share of the shared weights' gradients in row order, and the chunks'
partial sums are added in chunk order; the rows' gradients for the voxel projections are
scattered serially afterwards. Every sum along the chunk runs in a loop that stores nothing:
LLVM versions a vectorised loop that stores with a scalar copy, taken when a run-time check
cannot rule out overlapping arrays (so by where the scratch lands in memory), and under
fast-math a sum rounds differently in the two copies (vector lanes against one running total;
this broke the sampling kernels' thread test once, see :mod:`.gpdfn_sampling_kernels`). The
loops that store are element-wise, the same arithmetic in either copy. So every run, on any
number of threads, gives the same bits.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .gpdfn_kernels import of_dtype

#: Gaussians per chunk: the unit of parallel work and of the weights' partial gradient sums
#: (a chunk's scratch, ~3 x 16 x 64 values per array, stays in the CPU cache; 64, 256 and 1024
#: measured within ~25 % of each other at 70k Gaussians, 64 the fastest).
CHUNK = 64


@njit(cache=True, inline="always", fastmath=True)
def _stack(c, own, projection, index, weight, bias1, weight2, bias2, attention_weight, attention_bias,
           first, second, probability):
    """Fill ``first``/``second`` [K, H, B] (the activations after each ReLU) and ``probability``
    [K, B] (the softmax of the entries' scores) for the Gaussians of chunk ``c`` (B = the chunk
    size, the scratch's last axis); returns (start, rows): its first Gaussian and how many it has."""
    fused, hidden, chunk = first.shape
    start = c * chunk
    rows = min(own.shape[0], start + chunk) - start
    zero = of_dtype(own, 0)  # (a literal 0 would make ``value if value > 0 else 0`` a float64)
    for b in range(rows):
        n = start + b
        for j in range(hidden):
            value = own[n, j]
            first[0, j, b] = value if value > 0 else zero
        for k in range(1, fused):
            row = index[k - 1, n]
            w = weight[k - 1, n]
            for j in range(hidden):
                value = w * projection[row, j] + bias1[j]
                first[k, j, b] = value if value > 0 else zero
    for k in range(fused):
        for i in range(hidden):
            for b in range(rows):
                second[k, i, b] = bias2[i]
            for j in range(hidden):
                coefficient = weight2[i, j]
                for b in range(rows):
                    second[k, i, b] += coefficient * first[k, j, b]
        for b in range(rows):
            probability[k, b] = attention_bias[0]
        for i in range(hidden):
            coefficient = attention_weight[i]
            for b in range(rows):
                value = second[k, i, b]
                value = value if value > 0 else zero
                second[k, i, b] = value
                probability[k, b] += coefficient * value
    for b in range(rows):
        largest = probability[0, b]
        for k in range(1, fused):
            largest = max(largest, probability[k, b])
        for k in range(fused):
            probability[k, b] = math.exp(probability[k, b] - largest)
        total = zero  # summed in a loop that stores nothing (see the module's note)
        for k in range(fused):
            total += probability[k, b]
        for k in range(fused):
            probability[k, b] /= total
    return start, rows


@njit(cache=True, parallel=True, fastmath=True)
def fusion_forward(own, projection, index, weight, bias1, weight2, bias2, attention_weight, attention_bias,
                   chunk):
    """Attention-weighted summaries [N, H] of the fused stacks.

    own [N, H] (the Gaussians' own first-layer values, bias included, before the ReLU),
    projection [V, H] (the voxels' first-layer projections), index [K-1, N] int64 (valid ids),
    weight [K-1, N] (kernel weights), bias1 [H], weight2 [H, H], bias2 [H], attention_weight [H],
    attention_bias [1]; all one float dtype, C-contiguous.
    """
    count, hidden = own.shape
    fused = index.shape[0] + 1
    summaries = np.empty_like(own)
    chunks = (count + chunk - 1) // chunk
    for c in prange(chunks):
        first = np.empty((fused, hidden, chunk), own.dtype)
        second = np.empty((fused, hidden, chunk), own.dtype)
        probability = np.empty((fused, chunk), own.dtype)
        start, rows = _stack(c, own, projection, index, weight, bias1, weight2, bias2, attention_weight,
                             attention_bias, first, second, probability)
        for b in range(rows):
            for i in range(hidden):
                value = probability[0, b] * second[0, i, b]
                for k in range(1, fused):
                    value += probability[k, b] * second[k, i, b]
                summaries[start + b, i] = value
    return summaries


@njit(cache=True, parallel=True, fastmath=True)
def fusion_backward(grad_summaries, own, projection, index, weight, bias1, weight2, bias2, attention_weight,
                    attention_bias, chunk):
    """Gradients of the summaries (see :func:`fusion_forward`, same inputs) given ``grad_summaries`` [N, H].

    Returns (grad_own [N, H], grad_weight [K-1, N], grad_rows [K-1, N, H] (each sampled entry's
    gradient of the voxel projection row it read: scatter with ``index``), grad_bias1 [H],
    grad_weight2 [H, H], grad_bias2 [H], grad_attention_weight [H], grad_attention_bias [1]).
    """
    count, hidden = own.shape
    neighbours = index.shape[0]
    fused = neighbours + 1
    dtype = own.dtype
    zero = of_dtype(own, 0)
    grad_own = np.empty_like(own)
    grad_weight = np.empty((neighbours, count), dtype)
    grad_rows = np.empty((neighbours, count, hidden), dtype)
    chunks = (count + chunk - 1) // chunk
    part_bias1 = np.zeros((chunks, hidden), dtype)
    part_weight2 = np.zeros((chunks, hidden, hidden), dtype)
    part_bias2 = np.zeros((chunks, hidden), dtype)
    part_attention_weight = np.zeros((chunks, hidden), dtype)
    part_attention_bias = np.zeros(chunks, dtype)
    for c in prange(chunks):
        first = np.empty((fused, hidden, chunk), dtype)
        second = np.empty((fused, hidden, chunk), dtype)
        probability = np.empty((fused, chunk), dtype)
        upstream = np.empty((hidden, chunk), dtype)  # grad_summaries of the chunk, feature-major
        along = np.empty((fused, chunk), dtype)
        grad_score = np.empty(chunk, dtype)
        grad_second = np.empty((hidden, chunk), dtype)
        grad_first = np.empty((hidden, chunk), dtype)
        # this chunk's share of the shared weights' gradients (local: no writes to shared lines)
        # (np.empty and a plain loop: np.zeros here would be a nested parallel loop, which made
        # the threads contend so badly that two ran ~10x slower than one)
        sum_bias1 = np.empty(hidden, dtype)
        sum_weight2 = np.empty((hidden, hidden), dtype)
        sum_bias2 = np.empty(hidden, dtype)
        sum_attention_weight = np.empty(hidden, dtype)
        sum_attention_bias = np.empty(1, dtype)
        sum_attention_bias[0] = 0
        for i in range(hidden):
            sum_bias1[i] = 0
            sum_bias2[i] = 0
            sum_attention_weight[i] = 0
            for j in range(hidden):
                sum_weight2[i, j] = 0
        start, rows = _stack(c, own, projection, index, weight, bias1, weight2, bias2, attention_weight,
                             attention_bias, first, second, probability)
        for b in range(rows):
            for i in range(hidden):
                upstream[i, b] = grad_summaries[start + b, i]
        # softmax backward: d score_k = p_k (h_k . g - sum_l p_l h_l . g)
        for k in range(fused):
            for b in range(rows):
                along[k, b] = 0
            for i in range(hidden):
                for b in range(rows):
                    along[k, b] += second[k, i, b] * upstream[i, b]
        for k in range(fused):
            for b in range(rows):
                mean_along = probability[0, b] * along[0, b]
                for other in range(1, fused):
                    mean_along += probability[other, b] * along[other, b]
                grad_score[b] = probability[k, b] * (along[k, b] - mean_along)
            total = zero
            for b in range(rows):
                total += grad_score[b]
            sum_attention_bias[0] += total
            for i in range(hidden):
                coefficient = attention_weight[i]
                for b in range(rows):
                    # d h_k = p_k g + d score_k * attention_weight, through the second ReLU
                    gradient = probability[k, b] * upstream[i, b] + grad_score[b] * coefficient
                    grad_second[i, b] = gradient if second[k, i, b] > 0 else zero
                sum_weight = zero
                sum_bias = zero
                for b in range(rows):
                    sum_weight += grad_score[b] * second[k, i, b]
                    sum_bias += grad_second[i, b]
                sum_attention_weight[i] += sum_weight
                sum_bias2[i] += sum_bias
            for j in range(hidden):
                for b in range(rows):
                    grad_first[j, b] = 0
            for i in range(hidden):
                for j in range(hidden):
                    coefficient = weight2[i, j]
                    for b in range(rows):
                        grad_first[j, b] += coefficient * grad_second[i, b]
                    # a sum in a loop of its own that stores nothing (see the module's note)
                    sum_weight = zero
                    for b in range(rows):
                        sum_weight += grad_second[i, b] * first[k, j, b]
                    sum_weight2[i, j] += sum_weight
            for j in range(hidden):
                for b in range(rows):
                    grad_first[j, b] = grad_first[j, b] if first[k, j, b] > 0 else zero
            if k == 0:
                for b in range(rows):
                    for j in range(hidden):
                        grad_own[start + b, j] = grad_first[j, b]
            else:
                for j in range(hidden):
                    total = zero
                    for b in range(rows):
                        total += grad_first[j, b]
                    sum_bias1[j] += total
                for b in range(rows):
                    n = start + b
                    row = index[k - 1, n]
                    w = weight[k - 1, n]
                    for j in range(hidden):
                        grad_rows[k - 1, n, j] = grad_first[j, b] * w
                    along_projection = zero
                    for j in range(hidden):
                        along_projection += grad_first[j, b] * projection[row, j]
                    grad_weight[k - 1, n] = along_projection
        part_bias1[c] = sum_bias1
        part_weight2[c] = sum_weight2
        part_bias2[c] = sum_bias2
        part_attention_weight[c] = sum_attention_weight
        part_attention_bias[c] = sum_attention_bias[0]
    grad_bias1 = np.zeros(hidden, dtype)
    grad_weight2 = np.zeros((hidden, hidden), dtype)
    grad_bias2 = np.zeros(hidden, dtype)
    grad_attention_weight = np.zeros(hidden, dtype)
    grad_attention_bias = np.zeros(1, dtype)
    # in chunk order: the same sums on every thread count. Plain loops: an array expression
    # (``grad_bias1 += part_bias1[c]``) would be a parallel region of its own, launched once per
    # chunk (on Numba's TBB layer ~0.5 ms a launch: 20x the whole kernel)
    total = zero
    for c in range(chunks):
        total += part_attention_bias[c]
    grad_attention_bias[0] = total
    for c in range(chunks):
        for i in range(hidden):
            grad_bias1[i] += part_bias1[c, i]
            grad_bias2[i] += part_bias2[c, i]
            grad_attention_weight[i] += part_attention_weight[c, i]
            for j in range(hidden):
                grad_weight2[i, j] += part_weight2[c, i, j]
    return (grad_own, grad_weight, grad_rows, grad_bias1, grad_weight2, grad_bias2, grad_attention_weight,
            grad_attention_bias)
