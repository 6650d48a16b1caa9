"""The demo's Blender stage: a run beside its ground truth, compared, saved and pictured."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.errors import DatasetError
from esgs.core.formats.ply import GaussianPly, write_gaussians_ply
from tests.core.train.scene import make_scene


def _plane_run(tmp_path, offset: float):
    import trimesh

    scene = make_scene(tmp_path / "scene", views=3, width=32, height=24)
    plane = trimesh.Trimesh(vertices=[[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], faces=[[0, 1, 2], [0, 2, 3]])
    (scene / "mesh").mkdir()
    plane.export(scene / "mesh" / "ground_truth.ply")
    rng = np.random.default_rng(0)
    count = 400
    means = np.concatenate([rng.uniform(-1, 1, (count, 2)), np.full((count, 1), offset)], axis=1).astype(np.float32)
    gaussians = GaussianPly(means=means, normals=np.zeros_like(means), sh_dc=np.zeros((count, 3), np.float32),
                            sh_rest=np.zeros((count, 0, 3), np.float32), opacity_logit=np.full(count, 3.0, np.float32),
                            log_scales=np.full((count, 3), -4.0, np.float32),
                            quats_wxyz=np.tile(np.array([1, 0, 0, 0], np.float32), (count, 1)))
    run = tmp_path / "run"
    write_gaussians_ply(run / "point_cloud.ply", gaussians)
    return scene, run


def test_results_blend_measures_and_pictures_the_run(tmp_path):
    import bpy

    from esgs.esgs_addon.results_scene import build_results_blend

    scene, run = _plane_run(tmp_path, offset=0.03)
    summary = build_results_blend(scene, run, tmp_path / "out", threshold_m=0.05, picture_size=(64, 36))
    assert summary["gaussians_to_mesh"]["mean"] == pytest.approx(0.03, abs=1e-5)
    assert (tmp_path / "out" / "results.blend").stat().st_size > 0
    assert (tmp_path / "out" / "heat_map.png").stat().st_size > 0
    assert (tmp_path / "out" / "compare.json").is_file()
    assert "ground_truth" in bpy.data.objects and "gaussians" in bpy.data.objects
    distances = np.zeros(400, np.float32)
    bpy.data.objects["gaussians"].data.attributes["distance"].data.foreach_get("value", distances)
    np.testing.assert_allclose(distances, 0.03, atol=1e-5)


def test_missing_inputs_are_clear_errors(tmp_path):
    from esgs.esgs_addon.results_scene import build_results_blend

    scene, run = _plane_run(tmp_path, offset=0.0)
    with pytest.raises(DatasetError, match="no point_cloud.ply"):
        build_results_blend(scene, tmp_path / "nothing", tmp_path / "out")
    (scene / "mesh" / "ground_truth.ply").unlink()
    with pytest.raises(DatasetError, match="no ground-truth mesh"):
        build_results_blend(scene, run, tmp_path / "out")
