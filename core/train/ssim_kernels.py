"""The training loss's D-SSIM in two Numba passes, forward and backward (the ``cpu`` backend).

The torch statement of SSIM (:func:`esgs.core.metrics.image.ssim_map`) stacks five moment maps
(``x``, ``y``, ``x²``, ``y²``, ``xy``), blurs them with two depthwise convolutions and combines
them in about twenty elementwise passes; autograd then runs the convolutions' backward over
all fifteen channels and the passes' backward. Profiled at 100k Gaussians, 480x270, 2 threads,
that was ~45 ms of a ~400 ms 3DGS step (the convolutions alone 26 ms forward and 11 ms
backward), and more at high resolution (~350 ms forward at 1920x1080).

Here the forward blurs the five moments row by row and, per pixel, writes the SSIM's
derivatives with respect to the three moments that depend on the rendered image (its mean,
``E[x²]`` and ``E[xy]``); the backward blurs those three maps and combines them. The blur is
its own transpose (symmetric taps, zero padding: the same matrix either way), so the backward
is the forward's blur again: ``dS/dx = blur(dS/dmu) + 2x blur(dS/dE[x²]) + y blur(dS/dE[xy])``.

Images are ``[H, W * C]`` (an ``[H, W, C]`` image with its last two axes merged): a horizontal
tap is a shift of ``C`` along the row, so every loop runs along a whole row (contiguous,
vectorised) and nothing is permuted. Strict IEEE arithmetic (no fast-math): each output is a
sum of 11 taps in a fixed order and the SSIM total is summed row by row in float64, so every
call on any thread count gives the same bits.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange


#: Rows per block: a block blurs its rows and a halo of ``taps // 2`` rows on either side
#: horizontally into scratch of its own, then vertically; no image-sized temporaries (at
#: 1920x1080 the first touch of a [5, H, W*C] buffer alone cost ~240 ms in page faults).
BLOCK_ROWS = 32


@njit(cache=True, inline="always")
def _blur_row(source, taps, channels, out):
    """out[:] = the horizontal blur of the row ``source`` (zero padding; a tap steps ``channels``).

    1D slices in the inner loop: indexing a 2D array there kept LLVM from vectorising (7x slower).
    """
    length = source.shape[0]
    half = taps.shape[0] // 2
    for index in range(length):
        out[index] = 0
    for t in range(taps.shape[0]):
        shift = (t - half) * channels
        weight = taps[t]
        start = max(0, -shift)
        stop = min(length, length - shift)
        read = source[start + shift:stop + shift]
        write = out[start:stop]
        for index in range(stop - start):
            write[index] += weight * read[index]


@njit(cache=True, inline="always")
def _block_rows(block_index, block, height, half):
    """(first, last): the rows block ``block_index`` writes; (top, bottom): the rows its vertical
    blur reads (a halo of ``half`` rows either side, within the image)."""
    first = block_index * block
    last = min(height, first + block)
    return first, last, max(0, first - half), min(height, last + half)


@njit(cache=True, inline="always")
def _blur_column(scratch, first_row, row, height, taps, out):
    """out[m, :] = the vertical blur at ``row`` of ``scratch[m]`` (rows from ``first_row`` on; zero padding)."""
    half = taps.shape[0] // 2
    for m in range(out.shape[0]):
        target = out[m]
        for index in range(target.shape[0]):
            target[index] = 0
    for t in range(taps.shape[0]):
        source = row + t - half
        if source < 0 or source >= height:
            continue
        weight = taps[t]
        for m in range(out.shape[0]):
            read = scratch[m, source - first_row]
            target = out[m]
            for index in range(target.shape[0]):
                target[index] += weight * read[index]


@njit(cache=True, parallel=True)
def ssim_forward(x, y, taps, channels, constants, block=BLOCK_ROWS):
    """SSIM of ``x`` against ``y`` (both [H, W*C]) with its derivatives for the backward.

    ``taps`` [T] (odd, symmetric, normalised), ``constants`` [2] = (C1, C2), all in the images'
    dtype. Returns (totals [H] float64: each row's sum of the SSIM map, dmu [H, W*C], dxx, dxy:
    the per-pixel derivatives of SSIM with respect to the blurred x, E[x²] and E[xy]).
    """
    height, length = x.shape
    half = taps.shape[0] // 2
    dtype = x.dtype
    c1 = constants[0]
    c2 = constants[1]
    dmu = np.empty_like(x)
    dxx = np.empty_like(x)
    dxy = np.empty_like(x)
    totals = np.zeros(height, np.float64)
    blocks = (height + block - 1) // block
    for b in prange(blocks):
        first, last, top, bottom = _block_rows(b, block, height, half)
        scratch = np.empty((5, bottom - top, length), dtype)
        product = np.empty((3, length), dtype)
        moments = np.empty((5, length), dtype)
        values = np.empty(length, dtype)
        for row in range(top, bottom):
            a_row = x[row]
            b_row = y[row]
            for index in range(length):
                a = a_row[index]
                c = b_row[index]
                product[0, index] = a * a
                product[1, index] = c * c
                product[2, index] = a * c
            _blur_row(a_row, taps, channels, scratch[0, row - top])
            _blur_row(b_row, taps, channels, scratch[1, row - top])
            for moment in range(3):
                _blur_row(product[moment], taps, channels, scratch[2 + moment, row - top])
        for row in range(first, last):
            _blur_column(scratch, top, row, height, taps, moments)
            out_mu, out_xx, out_xy = dmu[row], dxx[row], dxy[row]
            for index in range(length):
                mu_x = moments[0, index]
                mu_y = moments[1, index]
                mu_xy = mu_x * mu_y
                mu_xx = mu_x * mu_x
                mu_yy = mu_y * mu_y
                a = mu_xy + mu_xy + c1
                b_ = (moments[4, index] - mu_xy) + (moments[4, index] - mu_xy) + c2
                c = mu_xx + mu_yy + c1
                d = (moments[2, index] - mu_xx) + (moments[3, index] - mu_yy) + c2
                cd = c * d
                value = a * b_ / cd
                values[index] = value
                # 1/c - 1/d written as (d - c)/(cd): a literal 1 would promote float32 to float64
                out_mu[index] = ((mu_y + mu_y) * (b_ - a) - (mu_x + mu_x) * value * (d - c)) / cd
                out_xx[index] = -value / d
                out_xy[index] = (a + a) / cd
            # summed in a loop of its own: a float64 running sum cannot vectorise, the loop above can
            total = 0.0
            for index in range(length):
                total += values[index]
            totals[row] = total
    return totals, dmu, dxx, dxy


@njit(cache=True, parallel=True)
def ssim_backward(x, y, dmu, dxx, dxy, taps, channels, scale, block=BLOCK_ROWS):
    """Gradient [H, W*C] of ``scale * sum(SSIM map)`` with respect to ``x`` (see :func:`ssim_forward`).

    ``scale``: a one-element array in the images' dtype (the upstream gradient over the count).
    """
    height, length = x.shape
    half = taps.shape[0] // 2
    dtype = x.dtype
    grad = np.empty_like(x)
    factor = scale[0]
    blocks = (height + block - 1) // block
    for b in prange(blocks):
        first, last, top, bottom = _block_rows(b, block, height, half)
        scratch = np.empty((3, bottom - top, length), dtype)
        blurred = np.empty((3, length), dtype)
        for row in range(top, bottom):
            _blur_row(dmu[row], taps, channels, scratch[0, row - top])
            _blur_row(dxx[row], taps, channels, scratch[1, row - top])
            _blur_row(dxy[row], taps, channels, scratch[2, row - top])
        for row in range(first, last):
            _blur_column(scratch, top, row, height, taps, blurred)
            a_row, c_row, out = x[row], y[row], grad[row]
            for index in range(length):
                a = a_row[index]
                out[index] = factor * (blurred[0, index] + (a + a) * blurred[1, index] + c_row[index] * blurred[2, index])
    return grad
