"""Keeping the training process lean: give freed heap memory back to the system.

glibc's malloc keeps memory that Python and torch have freed inside its heap, to reuse it
later. After loading a scene (image decoding, the COLMAP model's per-point Python objects,
the nearest-neighbour search of the initialisation) about 100 MiB of such free memory sits
in the heap, and the training steps only partly reuse it, so it raised the peak resident
size. ``malloc_trim`` hands free pages back at once. It never moves live memory: numbers
are unchanged. Elsewhere than on glibc (macOS, Windows, musl) the call is a no-op.

Measured effects are in docs/training.md ("Memory").
"""
from __future__ import annotations

import ctypes
import ctypes.util
import gc
import sys
from functools import lru_cache
from typing import Optional


@lru_cache(maxsize=1)
def _malloc_trim() -> Optional[object]:
    """glibc's ``malloc_trim`` or None where there is none."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):  # musl and other C libraries have no malloc_trim
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def release_free_memory(collect: bool = True) -> bool:
    """Collect garbage (``collect``) and return free heap pages to the system.

    Returns True when ``malloc_trim`` ran (glibc), False where it is not available.
    """
    if collect:
        gc.collect()
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


def resident_mib() -> Optional[float]:
    """This process's resident set size in MiB (Linux ``/proc``), or None elsewhere."""
    try:
        with open("/proc/self/statm", "rb") as handle:
            pages = int(handle.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    import os

    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
