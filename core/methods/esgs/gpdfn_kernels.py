"""Numba kernels of GPDFN's voxel table: voxel coordinates, a hash table of occupied voxels, lookups.

Voxel ``(i, j, k)`` of a point ``p`` is ``floor(p / voxel_size)`` computed in float32 (the
positions' precision), packed into one int64 key (21 bits per axis, offset by 2^20, as
:func:`pack_key`). The occupied voxels go into an open-addressing hash table (power-of-two
size, at least twice the voxel count, linear probing), so a sample point finds its voxel in
O(1) instead of a binary search over sorted keys (measured at 100k Gaussians: a NumPy
``searchsorted`` of 200k sample points cost ~18 ms, the hash lookup ~2 ms).

Voxel ids are given in order of first appearance in the Gaussian list, by one serial pass,
so the ids (and every sum over them) are the same on every run and thread count.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numba.extending import overload

_OFFSET = 1 << 20
_MASK = (1 << 21) - 1
_EMPTY = -1
# Fibonacci hashing: 0x9E3779B97F4A7C15 as a signed int64 (the multiplication wraps)
_HASH_MULTIPLIER = 0x9E3779B97F4A7C15 - (1 << 64)


def of_dtype(array: np.ndarray, value):
    """``value`` as a scalar of ``array``'s dtype (in the kernels: a typed zero, one or half).

    Numba types a literal or an int64 array element as int64 or float64, and float32 arithmetic
    with either is promoted to float64 (numpy's rules): a float32 kernel's ``x * 0``, ``1 - x``
    or ``x - coordinate - 0.5`` ran in float64, so its sums and vector loops at half the width.
    """
    return array.dtype.type(value)


@overload(of_dtype, inline="always")
def _of_dtype_in_kernels(array, value):
    kind = array.dtype

    def cast(array, value):
        return kind(value)
    return cast


@njit(cache=True, inline="always")
def pack_key(i: int, j: int, k: int) -> int:
    """One int64 key for voxel (i, j, k); coordinates are clamped to 21 bits each."""
    a = min(max(i + _OFFSET, 0), _MASK)
    b = min(max(j + _OFFSET, 0), _MASK)
    c = min(max(k + _OFFSET, 0), _MASK)
    return (a << 42) | (b << 21) | c


@njit(cache=True, inline="always")
def _slot(key: int, bits: int) -> int:
    # the top ``bits`` bits of the product (arithmetic shift, then masked)
    return ((key * _HASH_MULTIPLIER) >> (64 - bits)) & ((1 << bits) - 1)


@njit(cache=True, parallel=True)
def voxel_coordinates(points: np.ndarray, voxel_size: np.float32) -> tuple[np.ndarray, np.ndarray]:
    """points [M, 3] float32 -> (coordinates [M, 3] int64, keys [M] int64)."""
    count = points.shape[0]
    coordinates = np.empty((count, 3), dtype=np.int64)
    keys = np.empty(count, dtype=np.int64)
    for n in prange(count):
        i = int(math.floor(points[n, 0] / voxel_size))
        j = int(math.floor(points[n, 1] / voxel_size))
        k = int(math.floor(points[n, 2] / voxel_size))
        coordinates[n, 0] = i
        coordinates[n, 1] = j
        coordinates[n, 2] = k
        keys[n] = pack_key(i, j, k)
    return coordinates, keys


@njit(cache=True, inline="always")
def _table_bits(count: int) -> int:
    bits = 4
    while (1 << bits) < 2 * max(count, 1):
        bits += 1
    return bits


@njit(cache=True)
def _insert_all(keys: np.ndarray, slots: np.ndarray, bits: int, inverse: np.ndarray) -> int:
    """Insert ``keys`` in order into ``slots`` [S, 2] (key, id); ids by first appearance."""
    size = slots.shape[0]
    voxels = 0
    for n in range(keys.shape[0]):
        key = keys[n]
        slot = _slot(key, bits)
        while True:
            stored = slots[slot, 0]
            if stored == key:
                inverse[n] = slots[slot, 1]
                break
            if stored == _EMPTY:
                slots[slot, 0] = key
                slots[slot, 1] = voxels
                inverse[n] = voxels
                voxels += 1
                break
            slot = (slot + 1) & (size - 1)
    return voxels


@njit(cache=True)
def build_table(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hash table of the distinct keys [N] -> (slots [S, 2] int64 (key, voxel id), inverse [N] int64).

    ``inverse[n]`` is the voxel id of entry n; ids run 0..V-1 in order of first appearance.
    The table is built twice: once sized for N keys to find the V distinct ones, then sized
    for V, so the lookups probe a table ~N/V times smaller (fewer cache misses).
    """
    count = keys.shape[0]
    bits = _table_bits(count)
    scratch = np.full((1 << bits, 2), _EMPTY, dtype=np.int64)
    inverse = np.empty(count, dtype=np.int64)
    voxels = _insert_all(keys, scratch, bits, inverse)
    distinct = np.empty(voxels, dtype=np.int64)
    for slot in range(scratch.shape[0]):
        if scratch[slot, 0] != _EMPTY:
            distinct[scratch[slot, 1]] = scratch[slot, 0]
    bits = _table_bits(voxels)
    slots = np.full((1 << bits, 2), _EMPTY, dtype=np.int64)
    _insert_all(distinct, slots, bits, np.empty(voxels, dtype=np.int64))  # ids equal positions in distinct
    return slots, inverse


@njit(cache=True, inline="always")
def probe_bits(slots: np.ndarray) -> int:
    """log2 of the hash table's size (``slots`` [S, 2], S a power of two)."""
    bits = 0
    while (1 << bits) < slots.shape[0]:
        bits += 1
    return bits


@njit(cache=True, inline="always")
def find(x, y, z, voxel_size, slots: np.ndarray, bits: int) -> int:
    """Voxel id of the point (x, y, z) in the hash table ``slots``, -1 where the voxel is empty."""
    key = pack_key(int(math.floor(x / voxel_size)), int(math.floor(y / voxel_size)), int(math.floor(z / voxel_size)))
    size = slots.shape[0]
    slot = _slot(key, bits)
    while True:
        stored = slots[slot, 0]
        if stored == key:
            return slots[slot, 1]
        if stored == _EMPTY:
            return _EMPTY
        slot = (slot + 1) & (size - 1)


@njit(cache=True, parallel=True)
def lookup(points: np.ndarray, voxel_size, slots: np.ndarray) -> np.ndarray:
    """Voxel id of each point [M, 3] -> [M] int64 (-1 where the voxel is empty)."""
    bits = probe_bits(slots)
    count = points.shape[0]
    result = np.empty(count, dtype=np.int64)
    for n in prange(count):
        result[n] = find(points[n, 0], points[n, 1], points[n, 2], voxel_size, slots, bits)
    return result


@njit(cache=True)
def add_rows(target: np.ndarray, index: np.ndarray, source: np.ndarray) -> None:
    """``target[index[r]] += source[r]`` for every row r, in order (serial: the same sums every run).

    torch's ``index_add_`` on the CPU goes through a general scatter: ~6x slower for the
    [rows, 16] blocks of GPDFN's backward (measured at 8,192 rows: 0.41 against 0.07 ms).
    """
    columns = source.shape[1]
    for r in range(index.shape[0]):
        row = index[r]
        for c in range(columns):
            target[row, c] += source[r, c]
