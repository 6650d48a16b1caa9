"""3DGS PLY reader/writer against files written by hand from the format description."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from esgs.core.errors import FormatError
from esgs.core.formats.ply import GaussianPly, read_gaussians_ply, write_gaussians_ply
from tests.conftest import require_shared

FIXTURES = Path(__file__).parent / "fixtures"


def _header(fmt: str, count: int, properties: list[tuple[str, str]]) -> bytes:
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {count}"]
    lines += [f"property {kind} {name}" for kind, name in properties]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def _canonical_names(num_rest: int) -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * num_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def _handwritten_vertex(n: int, num_rest: int) -> dict[str, float]:
    """Distinct, exactly representable values for every property of Gaussian ``n``."""
    values = {}
    for i, name in enumerate(_canonical_names(num_rest)):
        values[name] = (n + 1) * 100.0 + i * 0.5 - 7.25  # multiples of 1/4: exact in float32
    return values


def _expect(vertices: list[dict[str, float]], num_rest: int) -> dict[str, np.ndarray]:
    """What the reader must return, derived from the layout rules (not from our writer)."""
    n = len(vertices)
    sh_rest = np.zeros((n, num_rest, 3), np.float32)
    for g, v in enumerate(vertices):
        for c in range(3):  # channel-major on disk: f_rest_{c*(K-1)+k} is coefficient k of channel c
            for k in range(num_rest):
                sh_rest[g, k, c] = v[f"f_rest_{c * num_rest + k}"]
    col = lambda *names: np.array([[v[name] for name in names] for v in vertices], np.float32)  # noqa: E731
    return {
        "means": col("x", "y", "z"),
        "normals": col("nx", "ny", "nz"),
        "sh_dc": col("f_dc_0", "f_dc_1", "f_dc_2"),
        "sh_rest": sh_rest,
        "opacity_logit": col("opacity")[:, 0],
        "log_scales": col("scale_0", "scale_1", "scale_2"),
        "quats_wxyz": col("rot_0", "rot_1", "rot_2", "rot_3"),
    }


def _assert_equal(gaussians: GaussianPly, expected: dict[str, np.ndarray]) -> None:
    for name, value in expected.items():
        got = getattr(gaussians, name)
        assert got.dtype == np.float32, name
        np.testing.assert_array_equal(got, value, err_msg=name)


def test_reads_handwritten_binary_little_endian_degree_1(tmp_path):
    num_rest = 3  # SH degree 1: K = 4
    vertices = [_handwritten_vertex(n, num_rest) for n in range(2)]
    names = _canonical_names(num_rest)
    data = _header("binary_little_endian", 2, [("float", name) for name in names])
    for v in vertices:
        data += struct.pack("<" + "f" * len(names), *(v[name] for name in names))
    path = tmp_path / "handwritten.ply"
    path.write_bytes(data)

    gaussians = read_gaussians_ply(path)
    assert len(gaussians) == 2 and gaussians.sh_degree == 1
    _assert_equal(gaussians, _expect(vertices, num_rest))
    # spot-check the channel-major rule directly: green (c=1), coefficient k=2 is f_rest_5
    assert gaussians.sh_rest[1, 2, 1] == vertices[1]["f_rest_5"]


def test_reads_reordered_big_endian_doubles_with_extra_properties(tmp_path):
    """Other tools' files: shuffled order, doubles, an extra uchar colour, no normals."""
    num_rest = 8  # SH degree 2
    vertices = [_handwritten_vertex(n, num_rest) for n in range(3)]
    names = [name for name in _canonical_names(num_rest) if name not in ("nx", "ny", "nz")]
    rng = np.random.default_rng(5)
    order = list(rng.permutation(names)) + ["red"]
    properties = [("uchar" if name == "red" else "double", name) for name in order]
    data = _header("binary_big_endian", 3, properties)
    for g, v in enumerate(vertices):
        for kind, name in properties:
            data += struct.pack(">B", 10 + g) if kind == "uchar" else struct.pack(">d", v[name])
    path = tmp_path / "other_tool.ply"
    path.write_bytes(data)

    gaussians = read_gaussians_ply(path)
    expected = _expect(vertices, num_rest)
    expected["normals"] = np.zeros((3, 3), np.float32)
    assert gaussians.sh_degree == 2
    _assert_equal(gaussians, expected)


def test_reads_handwritten_ascii_fixture():
    gaussians = read_gaussians_ply(FIXTURES / "gaussians_ascii_deg0.ply")
    assert len(gaussians) == 2 and gaussians.sh_degree == 0 and gaussians.sh_rest.shape == (2, 0, 3)
    np.testing.assert_array_equal(gaussians.means, [[1, 2, 3], [-4.5, 0, 7.75]])
    np.testing.assert_array_equal(gaussians.sh_dc, [[0.25, -0.25, 0.125], [1.5, 2.5, 3.5]])
    np.testing.assert_array_equal(gaussians.opacity_logit, [0.5, -2.5])
    np.testing.assert_array_equal(gaussians.log_scales, [[-1, -2, -3], [0, 0.5, -0.5]])
    np.testing.assert_array_equal(gaussians.quats_wxyz, [[1, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]])
    np.testing.assert_array_equal(gaussians.normals, np.zeros((2, 3)))


def _random_gaussians(n: int, degree: int, seed: int) -> GaussianPly:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return GaussianPly(
        means=rng.normal(size=(n, 3)) * 10,
        normals=np.zeros((n, 3)),
        sh_dc=rng.normal(size=(n, 3)),
        sh_rest=rng.normal(size=(n, k - 1, 3)),
        opacity_logit=rng.normal(size=n) * 4,
        log_scales=rng.normal(size=(n, 3)) - 3,
        quats_wxyz=rng.normal(size=(n, 4)),
    )


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_is_bit_exact(tmp_path, degree):
    original = _random_gaussians(257, degree, seed=degree)
    original.log_scales[0, 0] = np.nan  # odd values survive unchanged too
    original.opacity_logit[1] = -np.inf
    path = tmp_path / f"deg{degree}.ply"
    write_gaussians_ply(path, original)
    back = read_gaussians_ply(path)
    assert back.sh_degree == degree
    for name in ("means", "normals", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats_wxyz"):
        a, b = getattr(original, name), getattr(back, name)
        assert a.shape == b.shape, name
        np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32), err_msg=name)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left behind


def test_the_file_does_not_depend_on_how_many_rows_are_written_at_a_time(tmp_path):
    """The writer converts a block of rows at a time (memory): every block size writes the same bytes."""
    gaussians = _random_gaussians(257, 3, seed=7)
    files = []
    for rows in (1, 7, 256, 257, 100_000):
        path = tmp_path / f"rows{rows}.ply"
        write_gaussians_ply(path, gaussians, rows_per_write=rows)
        files.append(path.read_bytes())
    assert all(data == files[0] for data in files[1:])
    back = read_gaussians_ply(tmp_path / "rows7.ply")
    np.testing.assert_array_equal(back.sh_rest, gaussians.sh_rest.astype(np.float32))
    with pytest.raises(ValueError, match="rows_per_write"):
        write_gaussians_ply(tmp_path / "zero.ply", gaussians, rows_per_write=0)
    assert not (tmp_path / "zero.ply").exists()


def test_writer_uses_canonical_layout(tmp_path):
    """Header order and byte layout as the 3DGS description gives them, checked by hand."""
    gaussians = _random_gaussians(2, 3, seed=9)
    path = tmp_path / "g.ply"
    write_gaussians_ply(path, gaussians)
    raw = path.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    lines = [line for line in header.decode().splitlines() if not line.startswith("comment")]
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 2"]
    assert lines[3:] == [f"property float {name}" for name in _canonical_names(15)]
    assert len(body) == 2 * 62 * 4
    row = struct.unpack("<62f", body[62 * 4 :])  # second Gaussian
    g = 1
    assert row[0:3] == tuple(gaussians.means[g])
    assert row[6:9] == tuple(gaussians.sh_dc[g])
    assert row[9 + 15 * 2 + 4] == gaussians.sh_rest[g, 4, 2]  # blue block, coefficient 4
    assert row[54] == gaussians.opacity_logit[g]
    assert row[58:62] == tuple(gaussians.quats_wxyz[g])


def test_empty_cloud_round_trip(tmp_path):
    path = tmp_path / "empty.ply"
    write_gaussians_ply(path, _random_gaussians(0, 3, seed=0))
    back = read_gaussians_ply(path)
    assert len(back) == 0 and back.sh_rest.shape == (0, 15, 3)


def test_activated_helpers():
    gaussians = _random_gaussians(4, 0, seed=1)
    gaussians.opacity_logit[:] = [0.0, np.log(3.0), -np.log(3.0), 200.0]
    np.testing.assert_allclose(gaussians.opacities(), [0.5, 0.75, 0.25, 1.0], rtol=1e-6)
    gaussians.log_scales[0] = [0.0, np.log(2.0), -np.log(4.0)]
    np.testing.assert_allclose(gaussians.scales()[0], [1.0, 2.0, 0.25], rtol=1e-6)
    gaussians.quats_wxyz[0] = [2.0, 0.0, 0.0, 0.0]
    gaussians.quats_wxyz[1] = [0.0, 3.0, 0.0, 4.0]
    gaussians.quats_wxyz[2] = 0.0
    rotations = gaussians.rotations_normalised()
    np.testing.assert_allclose(rotations[:3], [[1, 0, 0, 0], [0, 0.6, 0, 0.8], [1, 0, 0, 0]], rtol=1e-6)


def test_truncated_file_is_a_format_error(tmp_path):
    path = tmp_path / "cut.ply"
    write_gaussians_ply(path, _random_gaussians(10, 1, seed=2))
    raw = path.read_bytes()
    path.write_bytes(raw[:-3])
    with pytest.raises(FormatError, match="truncated") as info:
        read_gaussians_ply(path)
    assert "cut.ply" in str(info.value)
    path.write_bytes(raw[:40])  # cut inside the header
    with pytest.raises(FormatError, match="end_header"):
        read_gaussians_ply(path)


def test_mesh_ply_is_a_format_error():
    mesh = require_shared("mars_landform", "terrain_geometry.ply")
    with pytest.raises(FormatError, match="not a 3D Gaussian Splatting PLY") as info:
        read_gaussians_ply(mesh)
    assert "terrain_geometry.ply" in str(info.value)


def test_other_bad_files(tmp_path):
    path = tmp_path / "not.ply"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(FormatError, match="not a PLY"):
        read_gaussians_ply(path)
    with pytest.raises(FormatError, match="cannot open"):
        read_gaussians_ply(tmp_path / "missing.ply")
    names = _canonical_names(0) + ["f_rest_0", "f_rest_1", "f_rest_2", "f_rest_3", "f_rest_4"]
    path.write_bytes(_header("binary_little_endian", 1, [("float", n) for n in names]) + bytes(4 * len(names)))
    with pytest.raises(FormatError, match="f_rest"):
        read_gaussians_ply(path)


def test_bad_shapes_are_rejected():
    from esgs.core.errors import ESGSError

    with pytest.raises(ESGSError, match="sh_rest"):
        GaussianPly(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 2, 3)),
                    np.zeros(2), np.zeros((2, 3)), np.zeros((2, 4)))
    with pytest.raises(ESGSError, match="quats_wxyz"):
        GaussianPly(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 0, 3)),
                    np.zeros(2), np.zeros((2, 3)), np.zeros((2, 3)))


def test_accepts_torch_tensors_with_grad(tmp_path):
    import torch

    source = _random_gaussians(5, 1, seed=3)
    tensors = {name: torch.from_numpy(getattr(source, name).copy()).requires_grad_(True)
               for name in ("means", "normals", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats_wxyz")}
    gaussians = GaussianPly(**tensors)
    assert isinstance(gaussians.means, np.ndarray) and gaussians.means.dtype == np.float32
    write_gaussians_ply(tmp_path / "t.ply", gaussians)
    np.testing.assert_array_equal(read_gaussians_ply(tmp_path / "t.ply").sh_rest, source.sh_rest)


def test_written_file_parses_with_an_independent_reader(tmp_path):
    """trimesh's own PLY parser sees the same property names and values as our layout promises."""
    import trimesh

    gaussians = _random_gaussians(6, 3, seed=4)
    path = tmp_path / "g.ply"
    write_gaussians_ply(path, gaussians)
    raw = trimesh.load(path, process=False).metadata["_ply_raw"]["vertex"]["data"]
    assert list(raw.dtype.names) == _canonical_names(15)
    for c in range(3):
        for k in range(15):
            np.testing.assert_array_equal(raw[f"f_rest_{c * 15 + k}"], gaussians.sh_rest[:, k, c])
    np.testing.assert_array_equal(raw["rot_0"], gaussians.quats_wxyz[:, 0])
    np.testing.assert_array_equal(raw["opacity"], gaussians.opacity_logit)
