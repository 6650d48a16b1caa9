"""Niantic's SPZ (the compressed splat format of Scaniverse), written through the optional ``gsply`` package.

We do not encode SPZ ourselves: ``gsply`` (``pip install gsply==0.4.6``, the ``spz`` extra) writes
it, and this module only maps our Gaussians onto gsply's ``GSData`` and picks the container.

What gsply 0.4.6 writes (``gsply/spz.py``; the layout of ``nianticlabs/spz``'s README): version 3,
the legacy container, one gzip stream of a 16-byte header (magic ``NGSP``, version, count, SH
degree, fractional bits, flags) then, per attribute, all Gaussians' bytes:

- positions: 3 x 24-bit signed fixed point with ``fractional_bits`` bits after the point
  (we use 12, SPZ's usual value, i.e. a step of 1/4096, unless the scene is too large: see
  :func:`spz_fractional_bits`);
- alphas: ``round(sigmoid(opacity) * 255)``: the opacity is stored activated;
- colours: ``round(f_dc * 0.15 * 255 + 127.5)``: the degree-0 SH coefficient (not an RGB colour),
  so ``f_dc`` outside about +-3.33 is clipped;
- scales: ``round((log_scale + 10) * 16)``: the log-scale, so outside [-10, 5.94] is clipped;
- rotations: the normalised quaternion, x y z w in the file (gsply turns our w x y z round),
  "smallest three": the index of the largest component, the other three in 9 bits and a sign;
- SH rest: ``round(f_rest * 128 + 128)``, clipped to [-1, 127/128], coefficient-major with the
  colour channel innermost (the PLY's ``f_rest`` is channel-major; gsply's ``shN`` [N, K, 3] is
  our ``sh_rest`` layout, and it flattens it in SPZ's order). gsply keeps all 8 bits where
  Niantic's encoder drops to 5 bits (degree 1) and 4 bits (degrees 2, 3) by default; readers
  decode both the same way.

Coordinates are written as they are in the PLY. SPZ's README says the format holds RUB (OpenGL)
coordinates and that PLY usually holds RDF, but Niantic's library converts only when the caller
names a frame (the default, ``UNSPECIFIED``, converts nothing) and gsply never converts: a tool
that converts SPZ from RUB sees the export turned 180 degrees about x (y and z negated).
"""
from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType

import numpy as np

from ..errors import ConfigError, FormatError
from ..io_utils import atomic_path
from .ply import GaussianPly

__all__ = ["SPZ_FRACTIONAL_BITS", "SPZ_VERSION", "gsply_module", "spz_clipped", "spz_fractional_bits",
           "to_gsdata", "write_spz"]

#: Fraction bits of the 24-bit fixed-point positions: SPZ's usual 12 (a 1/4096 step, +-2048 range).
SPZ_FRACTIONAL_BITS = 12
#: The container written: 3, gzip, which every SPZ reader opens (4, zstd, is newer).
SPZ_VERSION = 3
#: The package version the export was checked with (requirements.txt pins it).
GSPLY_VERSION = "0.4.6"

_FIXED_MAX = (1 << 23) - 1  # the largest 24-bit signed integer


def gsply_module() -> ModuleType:
    """The ``gsply`` package; a ConfigError naming the install command when it is missing."""
    try:
        import gsply
    except ImportError as err:
        raise ConfigError("--format spz needs the gsply package, which is not installed",
                          hint=f"pip install gsply=={GSPLY_VERSION}, or export --format ply or splat") from err
    return gsply


def spz_fractional_bits(means: np.ndarray) -> int:
    """12, or fewer when a position would not fit the 24-bit fixed point (|x| * 2^bits <= 2^23 - 1).

    A FormatError when a position is not finite or lies beyond 2^22 units (not even 1 bit fits).
    """
    means = np.asarray(means, dtype=np.float64)
    if means.size and not np.all(np.isfinite(means)):
        raise FormatError(f"{int(np.sum(~np.all(np.isfinite(means), axis=1)))} Gaussians have non-finite "
                          "positions, which SPZ cannot store")
    extent = float(np.max(np.abs(means))) if means.size else 0.0
    bits = SPZ_FRACTIONAL_BITS
    while bits > 1 and extent * (1 << bits) > _FIXED_MAX:
        bits -= 1
    if extent * (1 << bits) > _FIXED_MAX:
        raise FormatError(f"positions reach {extent:g} units from the origin, beyond SPZ's 24-bit fixed point "
                          f"(at most {_FIXED_MAX / 2:g} with 1 fraction bit)")
    return bits


def spz_clipped(gaussians: GaussianPly) -> dict[str, int]:
    """How many values SPZ's byte ranges clip, by attribute (``f_dc``, ``scale``, ``f_rest``)."""
    dc_limit = 127.5 / (0.15 * 255.0)  # colour byte 0 or 255
    return {
        "f_dc": int(np.sum(np.abs(gaussians.sh_dc) > dc_limit + 0.5 / (0.15 * 255.0))),
        "scale": int(np.sum((gaussians.log_scales < -10.0 - 1 / 32) | (gaussians.log_scales > 5.9375 + 1 / 32))),
        "f_rest": int(np.sum((gaussians.sh_rest < -1.0 - 1 / 256) | (gaussians.sh_rest > 127 / 128 + 1 / 256))),
    }


def to_gsdata(gaussians: GaussianPly, gsply: ModuleType | None = None):
    """Our Gaussians as gsply's ``GSData`` in its "ply" format (the un-activated 3DGS values).

    means as they are; scales the log-scales; opacities the logits; quats w x y z, normalised here
    (a zero quaternion becomes the identity, as in our renderer); sh0 ``f_dc``; shN our ``sh_rest``
    [N, K, 3] (coefficient, then channel), or None at degree 0.
    """
    gsply = gsply or gsply_module()
    f32 = np.float32
    rest = np.ascontiguousarray(gaussians.sh_rest, dtype=f32)
    opacity = np.nan_to_num(gaussians.opacity_logit.astype(f32), nan=0.0)  # NaN: SPZ has no byte for it
    log_scales = np.nan_to_num(gaussians.log_scales.astype(f32), nan=-10.0)
    return gsply.GSData.from_arrays(
        means=np.ascontiguousarray(gaussians.means, dtype=f32),
        scales=np.ascontiguousarray(log_scales),
        quats=np.ascontiguousarray(gaussians.rotations_normalised(), dtype=f32),
        opacities=np.ascontiguousarray(opacity),
        sh0=np.ascontiguousarray(np.nan_to_num(gaussians.sh_dc.astype(f32), nan=0.0)),
        shN=np.nan_to_num(rest, nan=0.0) if rest.shape[1] else None,
        format="ply",
    )


def write_spz(path: str | Path, gaussians: GaussianPly) -> int:
    """Write ``gaussians`` as an SPZ file (version 3, gzip) at ``path``, atomically; returns the fraction bits."""
    gsply = gsply_module()
    bits = spz_fractional_bits(gaussians.means)
    data = to_gsdata(gaussians, gsply)
    with atomic_path(path) as tmp:
        gsply.write_spz(tmp, data, version=SPZ_VERSION, fractional_bits=bits)
        with open(tmp, "rb") as handle:  # on disk before the rename, as the other writers do
            os.fsync(handle.fileno())
    return bits
