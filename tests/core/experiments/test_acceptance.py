"""The acceptance study's parts: SfM points from the images with known poses, the verdict, the sky helpers."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.experiments.acceptance import plan_runs, scene_methods, scene_rows, verdict
from esgs.core.experiments.tables import mean_std

from .helpers import make_experiment_scene


def _look_down(eye):
    from tests.core.train.scene import look_at

    return look_at(np.asarray(eye, float), np.array([eye[0] * 0.3, eye[1] * 0.3, 0.0]), up=(0.0, 1.0, 0.0))


def _textured_plane_scene(root, views: int = 4, width: int = 240, height: int = 180):
    """Images of a richly textured plane z = 0 rendered by ray casting, with exact poses and no points."""
    import cv2

    from esgs.core.colmap.geometry import matrix_to_quat_wxyz
    from esgs.core.colmap.io import write_model
    from esgs.core.colmap.model import Camera, ColmapModel, Image
    from esgs.core.formats.imageio import write_png

    rng = np.random.default_rng(0)
    texture = np.zeros((1024, 1024), np.float32)
    for sigma in (1.0, 3.0, 9.0):  # several scales of blobs: SIFT finds corners at each
        texture += cv2.GaussianBlur(rng.random((1024, 1024)).astype(np.float32), (0, 0), sigma) * sigma
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    fx = 200.0
    K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1]])
    (root / "images").mkdir(parents=True)
    images, views_out = {}, []
    for index in range(views):
        angle = 2 * np.pi * index / views
        eye = np.array([0.4 * np.cos(angle), 0.4 * np.sin(angle), 3.0])
        view = _look_down(eye)
        rotation, translation = view[:3, :3], view[:3, 3]
        u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        rays_cam = np.stack([(u - K[0, 2]) / fx, (v - K[1, 2]) / fx, np.ones_like(u)], -1)
        rays = rays_cam @ rotation  # camera -> world directions (R^T d)
        centre = -rotation.T @ translation
        t = -centre[2] / rays[..., 2]
        hit = centre + t[..., None] * rays
        map_x = ((hit[..., 0] + 2.0) / 4.0 * 1023).astype(np.float32)
        map_y = ((hit[..., 1] + 2.0) / 4.0 * 1023).astype(np.float32)
        grey = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR)
        name = f"view_{index:03d}.png"
        write_png(root / "images" / name, np.repeat((grey * 255).astype(np.uint8)[..., None], 3, axis=2))
        images[index + 1] = Image(index + 1, name, 1, matrix_to_quat_wxyz(rotation), translation)
        views_out.append((name, rotation, translation))
    cameras = {1: Camera(1, "PINHOLE", width, height, np.array([fx, fx, width / 2, height / 2]))}
    write_model(ColmapModel(cameras, images, {}), root / "sparse" / "0")
    return root, views_out


def test_sfm_scene_triangulates_the_images_with_the_known_poses(tmp_path):
    import pycolmap

    from esgs.core.colmap import read_model
    from esgs.core.experiments.sfm_scene import make_sfm_scene
    from esgs.core.priors import load_prior_maps

    scene, views = _textured_plane_scene(tmp_path / "plane")
    record = make_sfm_scene(scene, tmp_path / "plane_sfm")
    out = tmp_path / "plane_sfm"
    model = read_model(out)
    xyz = np.array([point.xyz for point in model.points.values()])
    assert record["points"] == len(xyz) > 100
    # real triangulations: on the plane to within a few mm (3 m away), not exactly
    assert np.median(np.abs(xyz[:, 2])) < 0.01 and record["mean_reprojection_error_px"] > 0
    reconstruction = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    for name, rotation, translation in views:  # poses kept
        pose = reconstruction.find_image_with_name(name).cam_from_world().matrix()
        np.testing.assert_allclose(pose[:, :3], rotation, atol=1e-9)
        np.testing.assert_allclose(pose[:, 3], translation, atol=1e-9)
    # sfm priors: depth at the observed pixels equals the plane's depth along z
    name, rotation, translation = views[0]
    maps = load_prior_maps(out, "sfm", name)
    rows, cols = np.nonzero(maps.mask)
    assert len(rows) > 20
    fx, cx, cy = 200.0, 120.0, 90.0
    rays = np.stack([(cols + 0.5 - cx) / fx, (rows + 0.5 - cy) / fx, np.ones_like(cols, float)], -1) @ rotation
    centre = -rotation.T @ translation
    plane_depth = -centre[2] / rays[:, 2]  # camera z of the plane along each pixel's ray (ray has z_cam = 1)
    # pixels are floor()ed keypoints (half a pixel of ray error); a few matches are wrong, as in any SfM
    relative = np.abs(maps.depth[rows, cols] - plane_depth) / plane_depth
    assert np.median(relative) < 0.005 and np.percentile(relative, 90) < 0.02


def _row(variant, **values):
    return {"variant": variant, "seeds": [0, 1, 2], **{key: mean_std(v) for key, v in values.items()}}


def test_verdict_requires_differences_beyond_the_seed_spread():
    base = _row("3DGS", ssim=[0.60, 0.61, 0.62], lpips=[0.30, 0.31, 0.32], distance_mean=[0.10, 0.11, 0.12],
                psnr=[20.0, 20.5, 21.0])
    good = _row("ESGS (sfm)", ssim=[0.65, 0.66, 0.67], lpips=[0.25, 0.26, 0.27], distance_mean=[0.05, 0.06, 0.07],
                psnr=[20.4, 20.5, 20.6])
    result = verdict(base, good)
    assert result["ssim"]["pass"] and result["lpips"]["pass"] and result["distance"]["pass"]
    assert result["distance"]["ratio"] == pytest.approx(0.06 / 0.11)
    assert result["psnr"]["change_db"] == pytest.approx(0.0) and result["psnr"]["significant"] is False
    # better means but within the spread, and only 15 % closer: all fail
    close = _row("ESGS (sfm)", ssim=[0.60, 0.62, 0.64], lpips=[0.28, 0.31, 0.34], distance_mean=[0.08, 0.095, 0.11],
                 psnr=[19.0, 19.0, 19.0])
    result = verdict(base, close)
    assert result["ssim"]["pass"] is False and result["lpips"]["pass"] is False and result["distance"]["pass"] is False
    assert result["psnr"]["change_db"] == pytest.approx(-1.5) and result["psnr"]["significant"]
    missing = _row("ESGS (sfm)", ssim=[0.7], lpips=[None], distance_mean=[None], psnr=[20.0])
    assert verdict(base, missing)["lpips"]["pass"] is None and verdict(base, missing)["distance"]["pass"] is None


def test_plan_runs_is_seed_first_with_every_source_and_rows_group_by_scene(tmp_path):
    scene = make_experiment_scene(tmp_path / "scene")
    assert [m.label for m in scene_methods(scene)] == ["3DGS", "ESGS (gt)"]
    full = dict(scene_methods(scene)[1].esgs)  # the full method, as esgs.core.methods.full_esgs defines it
    assert {key: full[key] for key in ("priors", "depth", "normal", "gpdfn", "fused_k")} == \
        {"priors": "gt", "depth": True, "normal": True, "gpdfn": True, "fused_k": 3}
    tasks = plan_runs({"a": scene, "b": scene}, tmp_path / "out", iterations=7, seeds=[0, 1], train={"width": 16})
    assert [task.name for task in tasks[:4]] == ["a/3dgs/seed0", "a/esgs-gt/seed0", "b/3dgs/seed0", "b/esgs-gt/seed0"]
    assert tasks[-1].config == {"width": 16, "iterations": 7, "seed": 1, "method": "esgs",
                                "method_config": dict(scene_methods(scene)[1].esgs)}
    summaries = [{"scene": "a", "variant": "3DGS", "seed": s, "psnr": 20.0 + s, "steps": 500 + 100 * s} for s in (0, 1)]
    rows = scene_rows(summaries)
    assert rows["a"][0]["psnr"] == {"mean": 20.5, "std": 0.5, "n": 2} and rows["a"][0]["seeds"] == [0, 1]
    assert rows["a"][0]["steps"] == {"mean": 550.0, "std": 50.0, "n": 2}  # steps differ at equal training time
    # an ESGS option reaches every ESGS row and never the baseline
    tuned = plan_runs({"a": scene}, tmp_path / "tuned", iterations=7, seeds=[0], esgs_options={"depth_weight": 3.0})
    assert tuned[0].config["method_config"] is None and tuned[1].config["method_config"]["depth_weight"] == 3.0
    assert tuned[1].config["method_config"]["priors"] == "gt"


def test_sky_filled_priors_keep_the_surface_and_fill_the_sky(tmp_path):
    from esgs.core.experiments.sky import horizon_band, write_sky_filled_priors
    from esgs.core.priors import load_prior_maps
    from tests.core.methods.test_esgs_hooks import _write_gt_priors
    from tests.core.train.scene import make_scene

    scene = make_scene(tmp_path / "scene", views=3, width=32, height=24)
    _write_gt_priors(scene, sky_rows=4)
    assert write_sky_filled_priors(scene) == 3
    name = sorted(p.name for p in (scene / "images").iterdir())[0]
    gt = load_prior_maps(scene, "gt", name)
    filled = load_prior_maps(scene, "gt_skyfilled", name)
    surface = gt.mask
    np.testing.assert_array_equal(filled.mask, gt.mask)
    np.testing.assert_allclose(filled.depth[surface], gt.depth[surface])
    assert np.all(filled.depth[~surface] == gt.depth[surface].max())
    np.testing.assert_allclose(filled.normal[~surface], np.tile([0.0, 0.0, -1.0], ((~surface).sum(), 1)))
    mask = np.ones((10, 6), bool)
    mask[:3] = False
    band = horizon_band(mask, 2)
    assert band[3:5].all() and not band[5:].any() and not band[:3].any()


def test_sky_figures_split_the_held_out_error_between_sky_and_surface(tmp_path):
    import json
    import math

    from esgs.core.experiments.sky import sky_figures
    from esgs.core.train import TrainConfig, train
    from tests.core.methods.test_esgs_hooks import _write_gt_priors
    from tests.core.train.scene import make_scene

    scene = make_scene(tmp_path / "scene", views=6, width=32, height=24)
    _write_gt_priors(scene, sky_rows=4)
    run = tmp_path / "run"
    train(TrainConfig(scene=str(scene), out=str(run), iterations=4, backend="cpu", lpips=False, test_every=6,
                      mask_source="none", save_renders=False, checkpoint_every=0, densify_until=0, sh_degree=1))
    figures = sky_figures(run, scene, band_px=2)
    from esgs.core.priors import load_prior_maps

    held_out = sorted(p.name for p in (scene / "images").iterdir())[0]
    mask = load_prior_maps(scene, "gt", held_out).mask
    assert not mask[:4].any()
    assert figures["views"] == 1 and figures["sky_fraction"] == pytest.approx(float((~mask).mean()))
    # sky and surface errors pooled back give the whole image's PSNR of the evaluation
    mse = lambda psnr: 10 ** (-psnr / 10)  # noqa: E731
    fraction = figures["sky_fraction"]
    whole = fraction * mse(figures["psnr_sky"]) + (1 - fraction) * mse(figures["psnr_surface"])
    metrics = json.loads((run / "metrics.json").read_text())
    assert -10 * math.log10(whole) == pytest.approx(metrics["psnr"], abs=1e-3)
    assert 0.0 <= figures["alpha_sky"] <= 1.0 and figures["horizon_depth_error"] >= 0.0
