"""The priors/labels writer: standard format, honest masks, all-or-nothing replacement."""
from __future__ import annotations

import json

import numpy as np
import pytest

from esgs.core.formats.imageio import read_depth_exr, read_image, read_normal_exr
from esgs.core.labels.fill import FILLED, RENDERED
from esgs.core.labels.writer import LabelWriter
from esgs.core.priors.io import load_prior_maps


def view(hole: bool = True) -> tuple[np.ndarray, np.ndarray]:
    depth = np.full((24, 32), 5.0, np.float32)
    depth[:4] = 0.0  # sky
    if hole:
        depth[10:14, 10:14] = 0.0
    normal = np.zeros((24, 32, 3), np.float32)
    normal[..., 2] = -1.0
    normal[depth == 0] = 0.0
    return depth, normal


def test_labels_are_written_in_the_prior_format_with_flagged_fill(tmp_path):
    metadata = {"method": "mesh", "mesh": "/data/terrain.ply"}
    with LabelWriter(tmp_path, metadata) as writer:
        stats = writer.add("sub/a.png", *view())
        writer.add("b.jpg", *view(hole=False))
    assert stats["filled_fraction"] == pytest.approx(16 / (24 * 32))
    root = tmp_path / "priors" / "labels"
    mask = read_image(root / "mask" / "sub" / "a.png")
    assert set(np.unique(mask)) == {0, FILLED, RENDERED}
    assert np.all(mask[10:14, 10:14] == FILLED) and np.all(mask[:3] == 0)
    depth, header = read_depth_exr(root / "depth" / "sub" / "a.exr")
    np.testing.assert_allclose(depth[10:14, 10:14], 5.0, rtol=1e-5)
    assert header["source"] == "labels" and header["mesh"] == "/data/terrain.ply" and header["method"] == "mesh"
    assert header["filled_pixels"] == "16"
    normal, normal_header = read_normal_exr(root / "normal" / "b.exr")
    assert normal_header["frame"] == "camera_opencv"
    # the standard loader reads rendered and filled pixels as valid, sky as not
    maps = load_prior_maps(tmp_path, "labels", "sub/a.png")
    assert maps.mask[12, 12] and not maps.mask[0, 0] and maps.depth[12, 12] == pytest.approx(5.0)
    report = json.loads((root / "labels.json").read_text())
    assert [v["image"] for v in report["views"]] == ["sub/a.png", "b.jpg"] and report["mesh"] == "/data/terrain.ply"
    assert not list(tmp_path.glob(".labels.partial.*"))


def test_a_failure_leaves_the_previous_labels_untouched(tmp_path):
    with LabelWriter(tmp_path, {"method": "mesh", "mesh": "old.ply"}) as writer:
        writer.add("a.png", *view())
    before = sorted(p.relative_to(tmp_path) for p in (tmp_path / "priors").rglob("*"))
    with pytest.raises(RuntimeError, match="simulated"):
        with LabelWriter(tmp_path, {"method": "mesh", "mesh": "new.ply"}) as writer:
            writer.add("a.png", *view(hole=False))
            raise RuntimeError("simulated crash in the renderer")
    assert sorted(p.relative_to(tmp_path) for p in (tmp_path / "priors").rglob("*")) == before
    assert json.loads((tmp_path / "priors" / "labels" / "labels.json").read_text())["mesh"] == "old.ply"
    assert not list(tmp_path.glob(".labels.partial.*")) and not list((tmp_path / "priors").glob(".labels.old.*"))


def test_a_successful_run_replaces_the_previous_labels(tmp_path):
    with LabelWriter(tmp_path, {"mesh": "old.ply"}) as writer:
        writer.add("a.png", *view())
        writer.add("stale.png", *view())
    with LabelWriter(tmp_path, {"mesh": "new.ply"}) as writer:
        writer.add("a.png", *view(hole=False))
    root = tmp_path / "priors" / "labels"
    assert not (root / "depth" / "stale.exr").exists()
    assert json.loads((root / "labels.json").read_text())["mesh"] == "new.ply"


def test_a_mesh_no_camera_sees_writes_nothing(tmp_path):
    from esgs.core.errors import DatasetError

    empty = np.zeros((24, 32), np.float32), np.zeros((24, 32, 3), np.float32)
    with pytest.raises(DatasetError, match="no camera sees the mesh"):
        with LabelWriter(tmp_path, {"mesh": "elsewhere.ply"}) as writer:
            writer.add("a.png", *empty)
            writer.add("b.png", *empty)
    assert not (tmp_path / "priors").exists() and not list(tmp_path.glob(".labels.partial.*"))


def test_no_views_writes_nothing(tmp_path):
    from esgs.core.errors import DatasetError

    with pytest.raises(DatasetError, match="no views"):
        with LabelWriter(tmp_path, {}):
            pass
    assert not (tmp_path / "priors").exists() and not list(tmp_path.glob(".labels.partial.*"))
