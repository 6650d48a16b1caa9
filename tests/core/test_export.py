"""``esgs export``: the 3DGS PLY and antimatter15's .splat, read back with readers written from the formats."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from esgs.core.cli import main
from esgs.core.formats.ply import GaussianPly, write_gaussians_ply

C0 = 0.28209479177387814


def _gaussians(count: int = 200, degree: int = 3, seed: int = 0) -> GaussianPly:
    rng = np.random.default_rng(seed)
    rest = (degree + 1) ** 2 - 1
    return GaussianPly(
        means=rng.normal(size=(count, 3)) * 5, normals=np.zeros((count, 3)),
        sh_dc=rng.normal(size=(count, 3)) * 1.5, sh_rest=rng.normal(size=(count, rest, 3)) * 0.1,
        opacity_logit=rng.normal(size=count) * 3, log_scales=rng.normal(size=(count, 3)) - 3,
        quats_wxyz=rng.normal(size=(count, 4)) * 2,
    )


@pytest.fixture
def run(tmp_path):
    folder = tmp_path / "myrun"
    folder.mkdir()
    gaussians = _gaussians()
    write_gaussians_ply(folder / "point_cloud.ply", gaussians)
    return folder, gaussians


def _read_splat(path):
    """Records of a .splat file: 32 bytes each, 3 float32 position, 3 float32 scale, RGBA uint8, quaternion uint8 (w first)."""
    data = path.read_bytes()
    assert len(data) % 32 == 0
    out = []
    for offset in range(0, len(data), 32):
        values = struct.unpack_from("<3f3f4B4B", data, offset)
        out.append((np.array(values[0:3]), np.array(values[3:6]), np.array(values[6:10]), np.array(values[10:14])))
    return out


def test_splat_round_trip(run, tmp_path, capsys):
    folder, gaussians = run
    out = tmp_path / "shared.splat"
    assert main(["export", str(folder), "--format", "splat", "--out", str(out)]) == 0
    assert "200 Gaussians" in capsys.readouterr().out
    records = _read_splat(out)
    assert len(records) == len(gaussians)

    alpha = 1 / (1 + np.exp(-gaussians.opacity_logit.astype(np.float64)))
    scales = np.exp(gaussians.log_scales.astype(np.float64))
    # each record is one Gaussian: find it by its position
    seen = set()
    keys = []
    for position, scale, rgba, quat in records:
        index = int(np.argmin(np.linalg.norm(gaussians.means - position, axis=1)))
        seen.add(index)
        np.testing.assert_array_equal(position, gaussians.means[index])
        np.testing.assert_allclose(scale, scales[index], rtol=1e-6)
        colour = np.clip(np.append(0.5 + C0 * gaussians.sh_dc[index], alpha[index]) * 255, 0, 255)
        assert np.all(np.abs(rgba - colour) <= 1.0), (rgba, colour)
        q = gaussians.quats_wxyz[index] / np.linalg.norm(gaussians.quats_wxyz[index])
        assert np.all(np.abs((quat.astype(float) - 128) / 128 - np.clip(q, -1, 127 / 128)) <= 1 / 128 + 1e-6)
        keys.append(np.prod(scale.astype(np.float64)) * alpha[index])
    assert len(seen) == len(gaussians)
    # ordering: descending exp(sum of log-scales) * alpha
    assert all(a >= b for a, b in zip(keys, keys[1:]))


def test_ply_export_is_the_3dgs_ply(run, tmp_path, monkeypatch):
    folder, _ = run
    monkeypatch.chdir(tmp_path)
    assert main(["export", str(folder)]) == 0  # default: ply, <run name>.ply here
    assert (tmp_path / "myrun.ply").read_bytes() == (folder / "point_cloud.ply").read_bytes()
    # a PLY given directly, default out in the current folder
    assert main(["export", str(folder / "point_cloud.ply"), "--format", "splat"]) == 0
    assert (tmp_path / "point_cloud.splat").stat().st_size == 200 * 32


def test_export_errors(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["export", str(tmp_path / "empty"), "--format", "splat"]) == 1  # missing data
    assert "no point_cloud.ply" in capsys.readouterr().err
    ply = tmp_path / "g.ply"
    write_gaussians_ply(ply, _gaussians(count=3))
    assert main(["export", str(ply), "--format", "ply", "--out", str(ply)]) == 2  # a bad option value
    assert "--out is the file being exported" in capsys.readouterr().err
