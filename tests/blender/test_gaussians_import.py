"""Importing 3DGS PLY files as Gaussian point clouds (esgs_addon/gaussians_import.py)."""
from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from esgs.core.errors import ConfigError, FormatError  # noqa: E402
from esgs.esgs_addon import gaussian_nodes, gaussians_import  # noqa: E402
from esgs.esgs_addon.pointcloud import read_point_attribute  # noqa: E402

SH_C0 = 0.28209479177387814

# Three Gaussians, un-activated as a 3DGS PLY stores them. Degree 1 SH: 3 rest coefficients
# per channel, stored channel-major (f_rest_0..2 red, 3..5 green, 6..8 blue).
KNOWN = [
    dict(xyz=(1.0, 2.0, 3.0), dc=(0.0, 1.0, -1.0), rest=[(0.1, 0.2, 0.3), (0.4, 0.5, 0.6), (0.7, 0.8, 0.9)],
         opacity=0.0, log_scale=(0.0, math.log(2.0), math.log(0.5)), rot=(2.0, 0.0, 0.0, 0.0)),
    dict(xyz=(-4.5, 0.25, 0.0), dc=(10.0, -10.0, 0.5), rest=[(0.0, 0.0, 0.0)] * 3,
         opacity=2.0, log_scale=(-3.0, -2.0, -1.0), rot=(0.0, 0.0, 3.0, 4.0)),
    dict(xyz=(0.0, 0.0, -7.0), dc=(-0.5, 0.25, 0.75), rest=[(1.0, -1.0, 2.0)] * 3,
         opacity=-1.5, log_scale=(1.0, 0.0, -0.5), rot=(1.0, 1.0, 1.0, 1.0)),
]


def write_ply_by_hand(path: Path, gaussians: list[dict], truncate_bytes: int = 0) -> None:
    """A binary little-endian 3DGS PLY written from the format description, property by property."""
    n_rest = 3 * len(gaussians[0]["rest"])
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(n_rest)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {len(gaussians)}\n"
    header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
    body = b""
    for g in gaussians:
        # rest[k][c] is coefficient k of channel c; the file stores all of red first
        rest = [g["rest"][k][c] for c in range(3) for k in range(len(g["rest"]))]
        values = [*g["xyz"], 0.0, 0.0, 0.0, *g["dc"], *rest, g["opacity"], *g["log_scale"], *g["rot"]]
        body += struct.pack("<" + "f" * len(values), *values)
    data = header.encode("ascii") + body
    path.write_bytes(data[: len(data) - truncate_bytes] if truncate_bytes else data)


def srgb_to_linear(value: float) -> float:
    return value / 12.92 if value <= 0.04045 else ((value + 0.055) / 1.055) ** 2.4


def datablock_counts() -> tuple[int, int, int, int, int]:
    return (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.pointclouds), len(bpy.data.node_groups),
            len(bpy.data.materials))


def test_known_gaussians_give_their_activated_values(tmp_path):
    path = tmp_path / "run" / "point_cloud.ply"
    path.parent.mkdir()
    write_ply_by_hand(path, KNOWN)
    obj = gaussians_import.import_gaussians(path, keep_sh=True)
    assert obj.type == "POINTCLOUD" and obj.name == "run"
    assert len(obj.data.points) == 3
    assert obj[gaussians_import.PROP_SH_DEGREE] == 1

    positions = gaussians_import.read_gaussian_arrays(obj)
    np.testing.assert_allclose(positions["position"], [g["xyz"] for g in KNOWN], atol=1e-6)
    np.testing.assert_allclose(positions["opacity"], [1 / (1 + math.exp(-g["opacity"])) for g in KNOWN], atol=1e-6)
    np.testing.assert_allclose(read_point_attribute(obj, "scale"),
                               [[math.exp(v) for v in g["log_scale"]] for g in KNOWN], rtol=1e-6)
    np.testing.assert_allclose(positions["rotation"], [[1, 0, 0, 0], [0, 0, 0.6, 0.8], [0.5, 0.5, 0.5, 0.5]],
                               atol=1e-6)
    expected_colour = [[srgb_to_linear(min(max(0.5 + SH_C0 * d, 0.0), 1.0)) for d in g["dc"]] + [1.0] for g in KNOWN]
    np.testing.assert_allclose(read_point_attribute(obj, "color"), expected_colour, atol=1e-6)
    # clamping: dc = +10 / -10 are white / black
    assert read_point_attribute(obj, "color")[1, 0] == pytest.approx(1.0)
    assert read_point_attribute(obj, "color")[1, 1] == pytest.approx(0.0)
    np.testing.assert_allclose(read_point_attribute(obj, "sh_dc"), [g["dc"] for g in KNOWN], atol=1e-6)
    for k in range(3):
        np.testing.assert_allclose(read_point_attribute(obj, f"sh_rest_{k}"), [g["rest"][k] for g in KNOWN], atol=1e-6)


def evaluated_points(obj) -> int:
    depsgraph = bpy.context.evaluated_depsgraph_get()
    depsgraph.update()
    return len(obj.evaluated_get(depsgraph).data.points)


def random_gaussians(tmp_path: Path, n: int, seed: int = 0) -> tuple[Path, np.ndarray]:
    rng = np.random.default_rng(seed)
    logits = rng.normal(scale=2.0, size=n)
    gaussians = [dict(xyz=tuple(rng.normal(size=3)), dc=(0.0, 0.0, 0.0), rest=[], opacity=float(logits[i]),
                      log_scale=(-3.0, -3.0, -3.0), rot=(1.0, 0.0, 0.0, 0.0)) for i in range(n)]
    path = tmp_path / "random.ply"
    write_ply_by_hand(path, gaussians)
    return path, 1 / (1 + np.exp(-logits.astype(np.float32)))


def test_display_filters_by_opacity_and_caps_the_count(tmp_path):
    path, opacities = random_gaussians(tmp_path, 3000)
    obj = gaussians_import.import_gaussians(path, opacity_min=0.6)
    assert len(obj.data.points) == 3000  # the data keeps every Gaussian
    assert evaluated_points(obj) == int(np.sum(opacities >= np.float32(0.6)))
    gaussian_nodes.set_display_inputs(obj, opacity_min=0.0, max_display=1000)
    shown = evaluated_points(obj)
    assert 850 <= shown <= 1150  # a random subset of about Max Display
    gaussian_nodes.set_display_inputs(obj, max_display=0)
    assert evaluated_points(obj) == 0
    assert gaussian_nodes.display_input(obj, "Max Display") == 0


def test_ellipsoids_are_scaled_and_rotated_like_the_gaussians(tmp_path):
    path = tmp_path / "known.ply"
    write_ply_by_hand(path, KNOWN)
    obj = gaussians_import.import_gaussians(path, mode="ellipsoids")
    gaussian_nodes.set_display_inputs(obj, ellipsoid_size=3.0)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    depsgraph.update()
    matrices = [np.array(instance.matrix_world) for instance in depsgraph.object_instances
                if instance.is_instance and instance.parent and instance.parent.original == obj]
    assert len(matrices) == 3
    from esgs.core.colmap.geometry import quat_wxyz_to_matrix

    for g in KNOWN:
        match = [m for m in matrices if np.allclose(m[:3, 3], g["xyz"], atol=1e-5)]
        assert len(match) == 1
        expected = quat_wxyz_to_matrix(np.array(g["rot"]) / np.linalg.norm(g["rot"])) @ np.diag(
            3.0 * np.exp(g["log_scale"]))
        np.testing.assert_allclose(match[0][:3, :3], expected, atol=1e-5)


@pytest.mark.parametrize("problem", ["mesh", "truncated", "not_ply"])
def test_bad_files_raise_and_create_nothing(tmp_path, problem):
    path = tmp_path / "bad.ply"
    if problem == "mesh":
        path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
                         b"property float y\nproperty float z\nend_header\n" + struct.pack("<fff", 1, 2, 3))
    elif problem == "truncated":
        write_ply_by_hand(path, KNOWN, truncate_bytes=5)
    else:
        path.write_text("solid cube\nendsolid\n")
    before = datablock_counts()
    with pytest.raises(FormatError) as info:
        gaussians_import.import_gaussians(path)
    assert str(path) in str(info.value)
    assert datablock_counts() == before
    with pytest.raises(RuntimeError, match="bad.ply"):
        bpy.ops.esgs.import_gaussians(filepath=str(path))
    assert datablock_counts() == before


def test_bad_options_are_config_errors(tmp_path):
    path = tmp_path / "known.ply"
    write_ply_by_hand(path, KNOWN)
    before = datablock_counts()
    with pytest.raises(ConfigError, match="display mode"):
        gaussians_import.import_gaussians(path, mode="splats")
    with pytest.raises(ConfigError, match="opacity_min"):
        gaussians_import.import_gaussians(path, opacity_min=1.5)
    assert datablock_counts() == before


def test_failure_after_creation_leaves_nothing(tmp_path, monkeypatch):
    path = tmp_path / "known.ply"
    write_ply_by_hand(path, KNOWN)
    before = datablock_counts()

    def broken(*args, **kwargs):
        raise RuntimeError("simulated node failure")

    monkeypatch.setattr(gaussian_nodes, "add_gaussian_modifier", broken)
    with pytest.raises(RuntimeError, match="simulated"):
        gaussians_import.import_gaussians(path)
    assert datablock_counts()[:3] == before[:3]


def test_operator_imports_and_selects(tmp_path):
    path = tmp_path / "known.ply"
    write_ply_by_hand(path, KNOWN)
    settings = bpy.context.scene.esgs.gaussians
    settings.mode = "ellipsoids"
    settings.opacity_min = 0.5
    assert bpy.ops.esgs.import_gaussians(filepath=str(path)) == {"FINISHED"}
    obj = bpy.context.view_layer.objects.active
    assert gaussians_import.is_gaussian_object(obj)
    assert gaussian_nodes.display_input(obj, "Ellipsoids") is True or gaussian_nodes.display_input(obj, "Ellipsoids") == 1
    assert gaussian_nodes.display_input(obj, "Opacity Min") == pytest.approx(0.5)
    # two of the three known Gaussians have opacity >= 0.5 (sigmoid(0) = 0.5, sigmoid(2))
    assert sum(1 for i in bpy.context.evaluated_depsgraph_get().object_instances
               if i.is_instance and i.parent and i.parent.original == obj) == 2
