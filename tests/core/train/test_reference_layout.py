"""A finished run opens in the 3DGS reference code's tools: point_cloud/iteration_<N>/ and cameras.json.

The readers here are written from the formats' descriptions (the 3DGS reference code's
``train.py`` / ``scene/__init__.py`` / ``utils/camera_utils.py``), not from our writer.
"""
from __future__ import annotations

import json
import math
import re

import numpy as np

from esgs.core.train import train


def _read_ply_header(path):
    """(vertex count, [(type, name)...], header length) of a binary little-endian PLY."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    count, properties = None, []
    for line in lines[2:]:
        words = line.split()
        if words[0] == "element":
            assert words[1] == "vertex" and count is None, "one vertex element"
            count = int(words[2])
        elif words[0] == "property":
            properties.append((words[1], words[2]))
    return count, properties, end


def _quat_to_matrix(w, x, y, z):
    """COLMAP's qvec2rotmat (Hamilton, w first), the rotation world -> camera."""
    return np.array([
        [1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * z * x + 2 * w * y],
        [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
        [2 * z * x - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y],
    ])


def test_run_folder_has_the_3dgs_reference_layout(fast_config, tiny_scene):
    from esgs.core.colmap.io import parse_model

    config = fast_config(iterations=6, resolution=2, evaluate=False, sh_degree=3)
    result = train(config)
    run = result.run_dir

    # point_cloud/iteration_<N>/point_cloud.ply: the 3DGS layout, the same bytes as RUN/point_cloud.ply
    folders = sorted((run / "point_cloud").iterdir())
    assert [f.name for f in folders] == [f"iteration_{result.step}"]
    ply = folders[0] / "point_cloud.ply"
    assert ply.read_bytes() == (run / "point_cloud.ply").read_bytes()
    count, properties, header_length = _read_ply_header(ply)
    assert count == result.n_gaussians > 0
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert [name for _, name in properties] == expected
    assert {kind for kind, _ in properties} == {"float"}
    assert len(ply.read_bytes()) == header_length + count * 4 * len(expected)

    # cameras.json: every image, camera centre and camera-to-world rotation of its COLMAP pose
    cameras = json.loads((run / "cameras.json").read_text())
    model = parse_model(tiny_scene / "sparse" / "0")
    by_name = {image.name: image for image in model.images.values()}
    assert len(cameras) == len(by_name) == 10
    assert [c["id"] for c in cameras] == list(range(10))
    colmap_camera = model.cameras[1]
    for entry in cameras:
        assert set(entry) == {"id", "img_name", "width", "height", "position", "rotation", "fx", "fy"}
        image = by_name[entry["img_name"] + ".png"]
        w2c = _quat_to_matrix(*image.quat_wxyz)
        centre = -w2c.T @ np.asarray(image.translation)
        np.testing.assert_allclose(entry["position"], centre, atol=1e-5)
        np.testing.assert_allclose(np.array(entry["rotation"]), w2c.T, atol=1e-5)
        assert (entry["width"], entry["height"]) == (colmap_camera.width // 2, colmap_camera.height // 2)
        assert math.isclose(entry["fx"], colmap_camera.params[0] / 2, rel_tol=1e-5)
        assert math.isclose(entry["fy"], colmap_camera.params[1] / 2, rel_tol=1e-5)

    # cfg_args: the Namespace repr SIBR's viewer parses
    cfg = (run / "cfg_args").read_text()
    assert cfg.startswith("Namespace(") and cfg.endswith(")")
    assert re.search(r"sh_degree=3\b", cfg) and "white_background=False" in cfg
    assert f"source_path={str(tiny_scene.resolve())!r}" in cfg


def test_older_iteration_folders_are_removed(fast_config, tmp_path):
    # an interrupted run's iteration_<k> would otherwise outlive the resumed run's final model
    stale = tmp_path / "run" / "point_cloud" / "iteration_99"
    stale.mkdir(parents=True)
    (stale / "point_cloud.ply").write_bytes(b"stale")
    result = train(fast_config(iterations=4, evaluate=False))
    assert sorted(p.name for p in (result.run_dir / "point_cloud").iterdir()) == ["iteration_4"]
