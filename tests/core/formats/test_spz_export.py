"""``esgs export RUN --format spz`` (through gsply 0.4.6), read back and compared with our PLY.

The file is read twice: with gsply's own reader (``gsply.read_spz``), and, for the layout gsply's
reader and writer could get wrong together (header, section order, quaternion order, the SH
rest order), by hand from the gzip stream as ``nianticlabs/spz``'s README describes it.

Tolerances, from SPZ's quantisation (gsply's encoder rounds to the nearest step, its reader
decodes in float32):

- positions: 24-bit fixed point with ``b`` fraction bits (12 here): error <= 0.5 / 2^b;
- opacity: stored activated, ``round(sigmoid(logit) * 255)``; the reader returns a logit, so the
  activated opacities are compared: error <= 0.5 / 255 (+ 1e-5 for the float32 logit round trip);
- ``f_dc``: ``round(f_dc * 0.15 * 255 + 127.5)``, step 1 / 38.25: error <= 0.5 / 38.25 after
  clipping the reference to the byte range, [-127.5, 127.5] / 38.25 (about +-3.33);
- log-scales: ``round((s + 10) * 16)``: error <= 1/32 after clipping the reference to [-10, 5.9375];
- rotations: "smallest three", the three smaller components of the unit quaternion in 9 bits of
  magnitude over [0, 1/sqrt 2]: h = (1/sqrt 2) / 511 / 2 for those; the largest is recomputed as
  sqrt(1 - sum of squares), off by at most |q_small . e| / q_max <= (sqrt(3)/2 * sqrt(3) h) / (1/2)
  = 3h; compared component-wise with 3h after choosing the sign (q and -q are one rotation);
- ``f_rest``: ``round(f_rest * 128 + 128)``: error <= 1/256 after clipping the reference to
  [-1, 127/128].
"""
from __future__ import annotations

import gzip
import struct
import sys

import numpy as np
import pytest

from esgs.core.cli import main
from esgs.core.formats.ply import GaussianPly, write_gaussians_ply

gsply = pytest.importorskip("gsply")

POSITION_STEP = 1 / 4096
ALPHA_TOL = 0.5 / 255 + 1e-5
DC_STEP = 1 / (0.15 * 255)
DC_RANGE = 127.5 * DC_STEP
SCALE_TOL = 1 / 32 + 1e-6
QUAT_TOL = 3 * (1 / np.sqrt(2)) / 511 / 2 + 1e-6
REST_TOL = 1 / 256 + 1e-6


def _gaussians(count: int = 300, degree: int = 3, seed: int = 0, spread: float = 5.0) -> GaussianPly:
    rng = np.random.default_rng(seed)
    rest = (degree + 1) ** 2 - 1
    return GaussianPly(
        means=rng.normal(size=(count, 3)) * spread, normals=np.zeros((count, 3)),
        sh_dc=rng.normal(size=(count, 3)) * 1.5,  # a few beyond +-3.33: clipped by the colour byte
        sh_rest=rng.normal(size=(count, rest, 3)) * 0.4,  # a few beyond [-1, 1): clipped by the SH byte
        opacity_logit=rng.normal(size=count) * 3, log_scales=rng.normal(size=(count, 3)) * 2 - 3,
        quats_wxyz=rng.normal(size=(count, 4)) * 2,  # not normalised, as a trained PLY stores them
    )


@pytest.fixture
def run(tmp_path):
    folder = tmp_path / "myrun"
    folder.mkdir()
    gaussians = _gaussians()
    write_gaussians_ply(folder / "point_cloud.ply", gaussians)
    return folder, gaussians


def _sigmoid(x):
    return 1 / (1 + np.exp(-np.asarray(x, dtype=np.float64)))


def _unit_wxyz(q):
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _export(folder, out, capsys):
    assert main(["export", str(folder), "--format", "spz", "--out", str(out)]) == 0
    return capsys.readouterr().out


def test_spz_read_back_by_gsply_matches_our_ply(run, tmp_path, capsys):
    folder, g = run
    out = tmp_path / "shared.spz"
    printed = _export(folder, out, capsys)
    assert "300 Gaussians" in printed and "positions to 1/4096" in printed and "clipped" in printed
    back = gsply.read_spz(out)
    assert back.means.shape == (300, 3) and back.shN.shape == (300, 15, 3)  # SPZ keeps the order

    np.testing.assert_allclose(back.means, g.means, rtol=0, atol=0.5 * POSITION_STEP + 1e-7)
    # opacity: SPZ stores alpha; gsply hands back a logit; compare activated values
    np.testing.assert_allclose(_sigmoid(back.opacities), _sigmoid(g.opacity_logit), rtol=0, atol=ALPHA_TOL)
    np.testing.assert_allclose(back.sh0, np.clip(g.sh_dc, -DC_RANGE, DC_RANGE), rtol=0, atol=0.5 * DC_STEP + 1e-5)
    np.testing.assert_allclose(back.scales, np.clip(g.log_scales, -10, 5.9375), rtol=0, atol=SCALE_TOL)
    ours = _unit_wxyz(g.quats_wxyz)
    theirs = back.quats.astype(np.float64)
    sign = np.where(np.sum(ours * theirs, axis=1) < 0, -1.0, 1.0)
    np.testing.assert_allclose(theirs * sign[:, None], ours, rtol=0, atol=QUAT_TOL)
    # SH rest, coefficient k and channel c of every Gaussian: a transposed layout would be far off
    np.testing.assert_allclose(back.shN, np.clip(g.sh_rest, -1, 127 / 128), rtol=0, atol=REST_TOL)
    assert np.any(np.abs(g.sh_rest) > 1) and np.any(np.abs(g.sh_dc) > DC_RANGE)  # the clipping was exercised


def test_spz_bytes_follow_nianticlabs_layout(run, tmp_path, capsys):
    """Header, section order, quaternion x y z w order and the SH rest order, read by hand."""
    folder, g = run
    out = tmp_path / "shared.spz"
    _export(folder, out, capsys)
    raw = gzip.decompress(out.read_bytes())
    magic, version, count, degree, bits, flags, reserved = struct.unpack_from("<IIIBBBB", raw, 0)
    assert (magic, version, count, degree, bits, flags, reserved) == (0x5053474E, 3, 300, 3, 12, 0, 0)
    n = count
    body = np.frombuffer(raw, dtype=np.uint8, offset=16)
    assert body.size == n * (9 + 1 + 3 + 3 + 4 + 45)
    positions, alphas, colours, scales, rotations, sh = np.split(
        body, np.cumsum([9 * n, n, 3 * n, 3 * n, 4 * n]))
    # positions: little-endian 24-bit signed, x y z
    p = positions.reshape(n, 3, 3).astype(np.int32)
    fixed = p[..., 0] | (p[..., 1] << 8) | (p[..., 2] << 16)
    fixed = np.where(fixed >= 1 << 23, fixed - (1 << 24), fixed)
    np.testing.assert_allclose(fixed / 4096, g.means, rtol=0, atol=0.5 * POSITION_STEP + 1e-7)
    np.testing.assert_allclose(alphas / 255, _sigmoid(g.opacity_logit), rtol=0, atol=0.5 / 255 + 1e-6)
    np.testing.assert_array_equal(colours.reshape(n, 3),
                                  np.clip(np.round(g.sh_dc * 0.15 * 255 + 127.5), 0, 255))
    np.testing.assert_array_equal(scales.reshape(n, 3), np.clip(np.round((g.log_scales + 10) * 16), 0, 255))
    # rotation: the top 2 bits index the largest |component| in x y z w order (w last)
    packed = rotations.reshape(n, 4).astype(np.uint32)
    word = packed[:, 0] | (packed[:, 1] << 8) | (packed[:, 2] << 16) | (packed[:, 3] << 24)
    xyzw = np.roll(_unit_wxyz(g.quats_wxyz), -1, axis=1)
    np.testing.assert_array_equal(word >> 30, np.argmax(np.abs(xyzw), axis=1))
    # SH rest: for each Gaussian 15 coefficients x (r, g, b), the channel innermost
    expected = np.clip(np.round(g.sh_rest.reshape(n, 45).astype(np.float64) * 128 + 128), 0, 255)
    assert np.max(np.abs(sh.reshape(n, 45).astype(np.float64) - expected)) <= 1  # float32 vs float64 rounding


def test_gsply_reads_our_ply_exactly(run):
    folder, g = run
    ply = gsply.plyread(folder / "point_cloud.ply")
    np.testing.assert_array_equal(ply.means, g.means)
    np.testing.assert_array_equal(ply.scales, g.log_scales)  # log-scales, as stored
    np.testing.assert_array_equal(ply.opacities, g.opacity_logit)  # logits, as stored
    np.testing.assert_array_equal(ply.quats, g.quats_wxyz)  # w x y z, not normalised
    np.testing.assert_array_equal(ply.sh0, g.sh_dc)
    np.testing.assert_array_equal(ply.shN, g.sh_rest)  # [N, K, 3] from our channel-major f_rest


@pytest.mark.parametrize("degree", [0, 1])
def test_lower_sh_degrees(tmp_path, capsys, degree):
    g = _gaussians(count=50, degree=degree, seed=degree)
    ply = tmp_path / "g.ply"
    write_gaussians_ply(ply, g)
    out = tmp_path / "g.spz"
    assert main(["export", str(ply), "--format", "spz", "--out", str(out)]) == 0
    back = gsply.read_spz(out)
    assert struct.unpack_from("<B", gzip.decompress(out.read_bytes()), 12)[0] == degree
    if degree:
        np.testing.assert_allclose(back.shN, np.clip(g.sh_rest, -1, 127 / 128), rtol=0, atol=REST_TOL)
    else:
        assert back.shN is None or back.shN.size == 0


def test_a_large_scene_gets_fewer_fraction_bits(tmp_path, capsys):
    g = _gaussians(count=40, spread=3000.0)  # beyond +-2048: 12 fraction bits would clip
    ply = tmp_path / "big.ply"
    write_gaussians_ply(ply, g)
    out = tmp_path / "big.spz"
    assert main(["export", str(ply), "--format", "spz", "--out", str(out)]) == 0
    bits = struct.unpack_from("<B", gzip.decompress(out.read_bytes()), 13)[0]
    assert bits < 12 and f"positions to 1/{1 << bits}" in capsys.readouterr().out
    assert np.max(np.abs(g.means)) * (1 << bits) <= (1 << 23) - 1
    np.testing.assert_allclose(gsply.read_spz(out).means, g.means, rtol=0, atol=0.5 / (1 << bits) + 1e-4)


def test_without_gsply_the_error_names_the_install(run, tmp_path, capsys, monkeypatch):
    folder, _ = run
    monkeypatch.setitem(sys.modules, "gsply", None)  # import gsply raises ImportError
    out = tmp_path / "x.spz"
    assert main(["export", str(folder), "--format", "spz", "--out", str(out)]) == 2  # ConfigError: bad usage
    err = capsys.readouterr().err
    assert "pip install gsply==0.4.6" in err and err.count("\n") == 1 and not out.exists()


def test_an_existing_file_is_replaced_atomically(run, tmp_path, capsys):
    folder, _ = run
    out = tmp_path / "shared.spz"
    out.write_bytes(b"old")
    _export(folder, out, capsys)
    assert gzip.decompress(out.read_bytes())[:4] == b"NGSP"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["myrun", "shared.spz"]  # no temporary left
