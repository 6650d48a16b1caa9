"""Numba kernels of GPDFN's per-Gaussian sampling on the CPU: features, offsets, voxel reads, first layer.

For every fused Gaussian, :class:`.gpdfn.GPDFN` builds its parameter vector (14 features), runs
the offset head (a 14 -> 3(K-1) linear layer and a tanh), places its ``K - 1`` sample points,
looks up the voxel holding each, weighs it by a Gaussian kernel of the distance to that voxel's
centroid, and applies the first pointwise layer to its own features. Written with torch that is
some twenty passes over ``[N, 14]``, ``[N, 16]`` and ``[K-1, N, 3]`` tensors and their backward
(index_select and its scatter, two small matrix products per linear layer, the tanh, the kernel
weights), each a trip to memory: at 300k Gaussians about as long as the fusion core itself.
Here each chunk of Gaussians goes through all of it in a few KB of scratch and writes only what
the fusion core reads (the own first-layer values, the voxel ids and kernel weights); the backward
recomputes the chunk and writes the parameters' gradients of its rows.

Same maths as the torch statements in :meth:`.gpdfn.GPDFN._voxel_averages` and
:meth:`.gpdfn.GPDFN._sample` (which stay the path on other devices and the tests' reference), in
the inputs' dtype (every constant is cast to it: :func:`.gpdfn_kernels.of_dtype`). Layout and determinism as
:mod:`.gpdfn_fusion_kernels`: chunks of fixed size in parallel, each chunk's activations
feature-major (inner loops along the chunk's Gaussians), the shared weights' gradients summed per
chunk and then in chunk order, so any thread count gives the same bits.
"""
from __future__ import annotations


import numpy as np
from numba import njit, prange

from .gpdfn_kernels import find, of_dtype, probe_bits

#: Features per Gaussian: position in its voxel 3, log-scale relative to the voxel 3, unit
#: quaternion 4, opacity logit 1, SH DC colour 3 (the order of ``GPDFN.gaussian_features``).
FEATURES = 14
#: Gaussians per chunk (the unit of parallel work and of the weights' partial sums).
CHUNK = 256


@njit(cache=True, inline="always")
def _features(start, rows_in_chunk, rows, means, log_scales, quats, opacity, dc, coordinates, voxel, log_voxel,
              features):
    """Fill ``features`` [14, B] with the parameter vectors of the chunk's Gaussians."""
    half = of_dtype(means, 0.5)
    for b in range(rows_in_chunk):
        n = rows[start + b]
        for a in range(3):
            features[a, b] = means[n, a] / voxel - of_dtype(means, coordinates[n, a]) - half
            features[3 + a, b] = log_scales[n, a] - log_voxel
            features[11 + a, b] = dc[n, a]
        for a in range(4):
            features[6 + a, b] = quats[n, a]
        features[10, b] = opacity[n]


@njit(cache=True, inline="always")
def _linear_backward(rows_in_chunk, upstream, rows_of_features, weight, grad_features, grad_weight, grad_bias):
    """Backward of ``outputs = weight[:, :14] @ features + bias`` over a chunk: adds into
    ``grad_features`` [14, B] and the chunk's weight [O, 14] and bias [O] sums; upstream [O, B];
    ``rows_of_features`` [B, 14] is the chunk's features Gaussian-major, so that the weights'
    sums run over the Gaussians in order while the loop along the 14 features vectorises."""
    for o in range(upstream.shape[0]):
        for i in range(FEATURES):
            coefficient = weight[o, i]
            for b in range(rows_in_chunk):
                grad_features[i, b] += coefficient * upstream[o, b]
    for b in range(rows_in_chunk):
        for o in range(upstream.shape[0]):
            value = upstream[o, b]
            grad_bias[o] += value
            for i in range(FEATURES):
                grad_weight[o, i] += value * rows_of_features[b, i]


# No fast-math flags in these kernels. LLVM versions a vectorised loop that stores with a scalar
# copy, taken when a run-time check cannot rule out overlapping arrays, so by where the scratch
# buffers land in memory; with reassociation (a sum in vector lanes against one running total)
# or reciprocals the two copies round differently, and a gradient changed in its last bits from
# one call to the next (CI caught it once; a few processes in ten here). In strict IEEE
# arithmetic both copies give the same bits and every sum runs in a fixed order; measured at
# 200k fused Gaussians, the fast-math flags bought nothing once the weights' sums run along the
# features (``_linear_backward``).


@njit(cache=True, parallel=True)
def sampling_layers(means, log_scales, quats, opacity, dc, rows, coordinates, offset_weight, offset_bias,
                    first_weight, first_bias, voxel, log_voxel, chunk):
    """The fused Gaussians' own first-layer values and offset-head pre-activations.

    means, log_scales, dc [N, 3], quats [N, 4] (unit), opacity [N] (logits): every Gaussian;
    rows [M] int64 (the fused ones); coordinates [N, 3] int64 (each Gaussian's voxel);
    offset_weight [3(K-1), 14], offset_bias [3(K-1)]; first_weight [H, 15] (the first layer: 14
    feature columns, then the weight channel's), first_bias [H]; voxel, log_voxel (``log(voxel)``):
    scalars of the dtype. Returns (own [M, H] = W[:, :14] features + W[:, 14] + bias,
    pre [3(K-1), M] = offset_weight features + offset_bias; the caller takes its tanh: a vector
    tanh in torch is ~7x faster than Numba's scalar one, which was half of this kernel's time).
    """
    count = rows.shape[0]
    outputs = offset_weight.shape[0]
    hidden = first_weight.shape[0]
    dtype = means.dtype
    own = np.empty((count, hidden), dtype)
    pre = np.empty((outputs, count), dtype)
    chunks = (count + chunk - 1) // chunk
    for c in prange(chunks):
        start = c * chunk
        size = min(count, start + chunk) - start
        features = np.empty((FEATURES, chunk), dtype)
        projected = np.empty((hidden, chunk), dtype)
        _features(start, size, rows, means, log_scales, quats, opacity, dc, coordinates, voxel, log_voxel, features)
        # one accumulator per Gaussian summed over the 14 features, vectorised along the chunk: one
        # store per output, not one per multiply-add (loops that stored every partial sum measured
        # slower in the fast-math build these kernels once had; not measured again since)
        for h in range(hidden):
            bias = first_bias[h] + first_weight[h, FEATURES]
            for b in range(size):
                value = bias
                for i in range(FEATURES):
                    value += first_weight[h, i] * features[i, b]
                projected[h, b] = value
        for b in range(size):
            for h in range(hidden):
                own[start + b, h] = projected[h, b]
        for j in range(outputs):
            bias = offset_bias[j]
            for b in range(size):
                value = bias
                for i in range(FEATURES):
                    value += offset_weight[j, i] * features[i, b]
                pre[j, start + b] = value
    return own, pre


@njit(cache=True, parallel=True)
def sampling_reads(means, rows, slots, centroids, base_offsets, shift, voxel, shift_scale, chunk):
    """Each fused Gaussian's sample points: the voxel holding each and the offset to its centroid.

    means [N, 3]; rows [M] int64; slots [S, 2] int64 (the voxel hash table); centroids [V, 3];
    base_offsets [K-1, 3] (voxel units); shift [3(K-1), M] (the offset head's tanh); voxel,
    shift_scale (largest shift times the voxel side): scalars of the dtype. The point of sample
    k is ``(mean + base_k voxel) + shift_k shift_scale`` (the torch statement's order). Returns
    (index [K-1, M] int64, 0 where the voxel is empty; squared [K-1, M], the squared distance to
    the centroid in voxels, infinite where the voxel is empty (the weight ``exp(-squared / 2)``
    is then 0); delta [K-1, 3, M], the offset to the centroid in voxels, 0 there).
    """
    count = rows.shape[0]
    neighbours = base_offsets.shape[0]
    dtype = means.dtype
    index = np.empty((neighbours, count), np.int64)
    squared = np.empty((neighbours, count), dtype)
    delta = np.empty((neighbours, 3, count), dtype)
    bits = probe_bits(slots)
    chunks = (count + chunk - 1) // chunk
    for c in prange(chunks):
        start = c * chunk
        end = min(count, start + chunk)
        for k in range(neighbours):
            for m in range(start, end):
                n = rows[m]
                x = (means[n, 0] + base_offsets[k, 0] * voxel) + shift[3 * k, m] * shift_scale
                y = (means[n, 1] + base_offsets[k, 1] * voxel) + shift[3 * k + 1, m] * shift_scale
                z = (means[n, 2] + base_offsets[k, 2] * voxel) + shift[3 * k + 2, m] * shift_scale
                found = find(x, y, z, voxel, slots, bits)
                if found < 0:
                    index[k, m] = 0
                    squared[k, m] = np.inf
                    delta[k, 0, m] = 0
                    delta[k, 1, m] = 0
                    delta[k, 2, m] = 0
                    continue
                dx = (x - centroids[found, 0]) / voxel
                dy = (y - centroids[found, 1]) / voxel
                dz = (z - centroids[found, 2]) / voxel
                index[k, m] = found
                squared[k, m] = dx * dx + dy * dy + dz * dz
                delta[k, 0, m] = dx
                delta[k, 1, m] = dy
                delta[k, 2, m] = dz
    return index, squared, delta


@njit(cache=True, parallel=True)
def sampling_backward(grad_own, grad_weight, weight, delta, shift, means, log_scales, quats, opacity, dc, rows,
                      coordinates, offset_weight, first_weight, voxel, log_voxel, shift_scale, chunk):
    """Gradients of the sampling given grad_own [M, H] and grad_weight [K-1, M].

    weight [K-1, M] (``exp(-squared / 2)``), delta [K-1, 3, M] and shift [3(K-1), M]: what the
    forward computed; the other inputs as :func:`sampling_layers`. The centroids are constants
    (the sampling reads them detached), so ``d weight / d point = -weight delta / voxel``.
    Returns (grad_means [N, 3], grad_log_scales [N, 3], grad_quats [N, 4], grad_opacity [N],
    grad_dc [N, 3]: zero outside ``rows``; grad_offset_weight, grad_offset_bias,
    grad_base_offsets [K-1, 3], grad_first_weight [H, 15], grad_first_bias [H]).
    """
    count = rows.shape[0]
    total = means.shape[0]
    neighbours = delta.shape[0]
    outputs = 3 * neighbours
    hidden = first_weight.shape[0]
    dtype = means.dtype
    zero, one = of_dtype(means, 0), of_dtype(means, 1)
    grad_means = np.zeros((total, 3), dtype)
    grad_log_scales = np.zeros((total, 3), dtype)
    grad_quats = np.zeros((total, 4), dtype)
    grad_opacity = np.zeros(total, dtype)
    grad_dc = np.zeros((total, 3), dtype)
    chunks = (count + chunk - 1) // chunk
    part_offset_weight = np.zeros((chunks, outputs, FEATURES), dtype)
    part_offset_bias = np.zeros((chunks, outputs), dtype)
    part_base = np.zeros((chunks, neighbours, 3), dtype)
    part_first_weight = np.zeros((chunks, hidden, FEATURES), dtype)
    part_first_bias = np.zeros((chunks, hidden), dtype)
    for c in prange(chunks):
        start = c * chunk
        size = min(count, start + chunk) - start
        upstream = np.empty((hidden, chunk), dtype)
        grad_features = np.empty((FEATURES, chunk), dtype)
        grad_pre = np.empty((outputs, chunk), dtype)
        grad_position = np.empty((3, chunk), dtype)  # the sample points' gradient reaching the means
        along = np.empty(chunk, dtype)  # one sample coordinate's gradient per Gaussian, summed in order below
        rows_of_features = np.empty((chunk, FEATURES), dtype)
        # (the transpose: _features fills the Gaussian-major rows directly)
        _features(start, size, rows, means, log_scales, quats, opacity, dc, coordinates, voxel, log_voxel,
                  rows_of_features.T)
        for i in range(FEATURES):
            for b in range(size):
                grad_features[i, b] = 0
        for b in range(size):
            for h in range(hidden):
                upstream[h, b] = grad_own[start + b, h]
        # own = W[:, :14] features + W[:, 14] + bias
        _linear_backward(size, upstream, rows_of_features, first_weight, grad_features, part_first_weight[c],
                         part_first_bias[c])
        # point = (mean + base voxel) + tanh(pre) shift_scale; weight = exp(-|delta|^2 / 2), delta = (point - centroid) / voxel
        for a in range(3):
            for b in range(size):
                grad_position[a, b] = 0
        for k in range(neighbours):
            for a in range(3):
                for b in range(size):
                    m = start + b
                    # (an empty voxel has weight 0 and delta 0: no gradient)
                    gradient = -grad_weight[k, m] * weight[k, m] * delta[k, a, m] / voxel
                    grad_position[a, b] += gradient
                    along[b] = gradient
                    value = shift[3 * k + a, m]
                    grad_pre[3 * k + a, b] = gradient * shift_scale * (one - value * value)
                summed = zero
                for b in range(size):
                    summed += along[b]
                part_base[c, k, a] += summed * voxel
        _linear_backward(size, grad_pre, rows_of_features, offset_weight, grad_features, part_offset_weight[c],
                         part_offset_bias[c])
        for b in range(size):
            n = rows[start + b]
            for a in range(3):
                grad_means[n, a] = grad_position[a, b] + grad_features[a, b] / voxel
                grad_log_scales[n, a] = grad_features[3 + a, b]
                grad_dc[n, a] = grad_features[11 + a, b]
            for a in range(4):
                grad_quats[n, a] = grad_features[6 + a, b]
            grad_opacity[n] = grad_features[10, b]
    grad_offset_weight = np.zeros((outputs, FEATURES), dtype)
    grad_offset_bias = np.zeros(outputs, dtype)
    grad_base = np.zeros((neighbours, 3), dtype)
    grad_first_weight = np.zeros((hidden, FEATURES + 1), dtype)
    grad_first_bias = np.zeros(hidden, dtype)
    # in chunk order, plain loops (see gpdfn_fusion_kernels: an array expression here would be a
    # parallel launch per chunk)
    for c in range(chunks):
        for j in range(outputs):
            grad_offset_bias[j] += part_offset_bias[c, j]
            for i in range(FEATURES):
                grad_offset_weight[j, i] += part_offset_weight[c, j, i]
        for k in range(neighbours):
            for a in range(3):
                grad_base[k, a] += part_base[c, k, a]
        for h in range(hidden):
            grad_first_bias[h] += part_first_bias[c, h]
            for i in range(FEATURES):
                grad_first_weight[h, i] += part_first_weight[c, h, i]
    for h in range(hidden):
        grad_first_weight[h, FEATURES] = grad_first_bias[h]  # the weight channel's input is 1
    return (grad_means, grad_log_scales, grad_quats, grad_opacity, grad_dc, grad_offset_weight, grad_offset_bias,
            grad_base, grad_first_weight, grad_first_bias)


@njit(cache=True)
def voxel_means(means, log_scales, quats, opacity, dc, coordinates, inverse, counts, voxel, log_voxel):
    """Each voxel's mean feature vector and centroid, from every Gaussian's parameters.

    The arrays as :func:`sampling_layers` (every Gaussian), inverse [N] int64 (voxel ids),
    counts [V] (Gaussians per voxel, float). Returns (features [V, 14], centroids [V, 3]).
    Serial, in Gaussian order: the same sums on every run (the torch path's ``add_rows_`` order).
    """
    voxels = counts.shape[0]
    dtype = means.dtype
    features = np.zeros((voxels, FEATURES), dtype)
    centroids = np.zeros((voxels, 3), dtype)
    half = of_dtype(means, 0.5)
    for n in range(means.shape[0]):
        v = inverse[n]
        for a in range(3):
            features[v, a] += means[n, a] / voxel - of_dtype(means, coordinates[n, a]) - half
            features[v, 3 + a] += log_scales[n, a] - log_voxel
            features[v, 11 + a] += dc[n, a]
            centroids[v, a] += means[n, a]
        for a in range(4):
            features[v, 6 + a] += quats[n, a]
        features[v, 10] += opacity[n]
    for v in range(voxels):
        for i in range(FEATURES):
            features[v, i] /= counts[v]
        for a in range(3):
            centroids[v, a] /= counts[v]
    return features, centroids


@njit(cache=True, parallel=True)
def voxel_means_backward(grad_features, inverse, counts, voxel):
    """Gradients of :func:`voxel_means`' features given grad_features [V, 14] (the centroids are
    constants) -> (grad_means [N, 3], grad_log_scales [N, 3], grad_quats [N, 4], grad_opacity [N],
    grad_dc [N, 3]): each Gaussian gets its voxel's gradient over the voxel's count."""
    total = inverse.shape[0]
    dtype = grad_features.dtype
    grad_means = np.empty((total, 3), dtype)
    grad_log_scales = np.empty((total, 3), dtype)
    grad_quats = np.empty((total, 4), dtype)
    grad_opacity = np.empty(total, dtype)
    grad_dc = np.empty((total, 3), dtype)
    for n in prange(total):
        v = inverse[n]
        share = counts[v]
        for a in range(3):
            grad_means[n, a] = grad_features[v, a] / share / voxel
            grad_log_scales[n, a] = grad_features[v, 3 + a] / share
            grad_dc[n, a] = grad_features[v, 11 + a] / share
        for a in range(4):
            grad_quats[n, a] = grad_features[v, 6 + a] / share
        grad_opacity[n] = grad_features[v, 10] / share
    return grad_means, grad_log_scales, grad_quats, grad_opacity, grad_dc
