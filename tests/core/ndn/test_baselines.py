"""NDN's baselines: sparse SfM depth interpolated, and the regression UNet (same network, no diffusion)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from esgs.core.ndn.baselines import (SparseDepth, densify_sparse_depth, normals_from_depth, sfm_baseline_maps,
                                     triangulate_known_poses)
from esgs.core.ndn.infer import score_view
from esgs.core.ndn.train import build_model, load_checkpoint, save_checkpoint

from .conftest import tiny_config


def test_densified_depth_is_exact_for_a_linear_field_and_nearest_outside():
    rng = np.random.default_rng(0)
    uv = rng.uniform([10, 5], [50, 25], (40, 2))
    depth = 3.0 + 0.05 * uv[:, 0] - 0.02 * uv[:, 1]
    dense = densify_sparse_depth(uv, depth, 64, 32)
    rows, columns = np.mgrid[0:32, 0:64] + 0.5
    truth = 3.0 + 0.05 * columns - 0.02 * rows
    from scipy.spatial import Delaunay

    inside = Delaunay(uv).find_simplex(np.stack([columns, rows], -1).reshape(-1, 2)).reshape(32, 64) >= 0
    np.testing.assert_allclose(dense[inside], truth[inside], rtol=1e-5)
    corner = np.argmin(np.hypot(uv[:, 0] - 0.5, uv[:, 1] - 0.5))
    assert dense[0, 0] == np.float32(depth[corner])  # nearest sample outside the hull
    assert densify_sparse_depth(uv[:0], depth[:0], 8, 8) is None
    np.testing.assert_array_equal(densify_sparse_depth(uv[:2], depth[:2], 8, 8).shape, (8, 8))


def test_normals_from_the_depth_of_a_tilted_plane_are_its_normal():
    fx = fy = 40.0
    width, height = 48, 27
    plane_normal = np.array([0.0, -0.6, -0.8])  # facing the camera (n . X < 0)
    rows, columns = np.mgrid[0:height, 0:width] + 0.5
    rays = np.stack([(columns - width / 2) / fx, (rows - height / 2) / fy, np.ones_like(columns)], axis=-1)
    depth = -4.0 / (rays @ plane_normal)
    normals = normals_from_depth(depth, fx, fy, width / 2, height / 2)
    np.testing.assert_allclose(normals.transpose(1, 2, 0), np.broadcast_to(plane_normal, (height, width, 3)),
                               atol=1e-6)


def test_a_view_without_points_gets_a_flat_uninformed_guess():
    depth, normal, has_points = sfm_baseline_maps(SparseDepth(np.zeros((0, 2)), np.zeros(0)), (160, 90), (128, 72),
                                                  np.array([100.0, 100.0, 80.0, 45.0]))
    assert not has_points and depth.shape == (72, 128) and np.ptp(depth) == 0
    assert (normal[2] == -1).all()


def _textured_plane_scene(root: Path) -> Path:
    """Four nadir cameras 5 m above a textured ground plane (z = 0), images by exact warping."""
    import cv2

    from esgs.core.colmap.geometry import matrix_to_quat_wxyz
    from esgs.core.colmap.io import write_model
    from esgs.core.colmap.model import Camera, ColmapModel, Image, Point3D
    from esgs.core.formats.imageio import write_png

    rng = np.random.default_rng(3)
    texture = np.zeros((1024, 1024), np.float32)
    for sigma in (2, 6, 16):
        texture += cv2.GaussianBlur(rng.normal(0, 1, (1024, 1024)).astype(np.float32), (0, 0), sigma) * sigma
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    width, height, focal, altitude, texels_per_m = 320, 180, 200.0, 5.0, 64.0
    rotation = np.diag([1.0, -1.0, -1.0])  # camera z looks down
    camera = Camera(1, "PINHOLE", width, height, np.array([focal, focal, width / 2, height / 2]))
    images = {}
    rows, columns = np.mgrid[0:height, 0:width].astype(np.float32) + 0.5
    for index in range(4):
        centre = np.array([0.6 * index - 0.9, 0.0, altitude])
        world_x = centre[0] + (columns - width / 2) / focal * altitude
        world_y = centre[1] - (rows - height / 2) / focal * altitude
        map_x = (world_x * texels_per_m + 512 - 0.5).astype(np.float32)
        map_y = (world_y * texels_per_m + 512 - 0.5).astype(np.float32)
        grey = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR)
        name = f"view_{index:03d}.png"
        write_png(root / "images" / name, np.repeat(grey[..., None], 3, axis=-1))
        images[index + 1] = Image(index + 1, name, 1, matrix_to_quat_wxyz(rotation), -rotation @ centre)
    points = {1: Point3D(1, np.zeros(3), np.array([128, 128, 128], np.uint8), 0.5)}
    write_model(ColmapModel({1: camera}, images, points), root / "sparse" / "0")
    return root


def test_triangulation_with_known_poses_finds_the_plane(tmp_path):
    scene = _textured_plane_scene(tmp_path / "plane")
    sparse = triangulate_known_poses(scene, upscale=1.0)
    assert sorted(sparse) == [f"view_{i:03d}.png" for i in range(4)]
    depths = np.concatenate([view.depth for view in sparse.values()])
    assert len(depths) >= 40
    assert np.median(np.abs(depths - 5.0)) < 0.05  # every point lies on the plane 5 m below
    for view in sparse.values():
        assert ((view.uv >= 0) & (view.uv <= [320, 180])).all()


def test_regression_baseline_is_the_same_network_trained_without_diffusion():
    torch.manual_seed(0)
    config = tiny_config("regression")
    model, diffusion = build_model(config)
    reference, _ = build_model(tiny_config("v"))
    assert sum(p.numel() for p in model.parameters()) == sum(p.numel() for p in reference.parameters())
    views = torch.rand(4, 9, 16, 32) * 2 - 1
    depth = views[:, :1].clone()  # a target the network can read from its input
    normal = torch.nn.functional.normalize(views[:, :3].clone(), dim=1)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        loss, parts = diffusion.training_loss(model, views, depth, normal)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0]
    # one forward pass: no noise, so the seed changes nothing; depth clipped to the state's range
    model.eval()
    first, second = diffusion.sample(model, views, seed=1), diffusion.sample(model, views, seed=2)
    torch.testing.assert_close(first, second)
    assert first[0].abs().max() <= 1.0
    with torch.no_grad():
        direct = model(views, torch.zeros(4, 1, 16, 32), torch.zeros(4, 3, 16, 32), torch.zeros(4, dtype=torch.long))
    torch.testing.assert_close(first[1], direct[1])


def test_regression_checkpoints_load_as_regression(tmp_path):
    model, _ = build_model(tiny_config("regression"))
    path = save_checkpoint(tmp_path / "r.pt", model, tiny_config("regression"))
    _, diffusion, config, _ = load_checkpoint(path)
    assert config.diffusion.prediction == "regression" and diffusion.regression


def test_scores_of_a_perfect_and_an_affine_prediction():
    rng = np.random.default_rng(1)
    truth = rng.uniform(2, 9, (12, 16)).astype(np.float32)
    normal = np.zeros((3, 12, 16), np.float32)
    normal[2] = -1
    mask = np.ones((12, 16), bool)
    scores = score_view(0.5 * truth + 3.0, normal, truth, normal, mask)
    assert scores["abs_rel"] < 1e-5 and scores["delta1"] == 1.0
    assert scores["normal_mean_deg"] < 0.1 and scores["normal_within_11_25"] == 1.0


def test_shard_command_adds_a_scene_folder_to_a_data_folder(tmp_path, capsys):
    from esgs.core.cli import main
    from esgs.core.ndn.data import load_shards, scene_triples

    from .conftest import make_scene

    scene = make_scene(tmp_path / "landform_orbit_1")
    assert main(["ndn", "shard", str(scene), "--data", str(tmp_path / "data"), "--working-size", "32",
                 "--multiple", "2"]) == 0
    assert (tmp_path / "data/shards/heldout_landform_orbit_1.npz").exists()
    arrays = load_shards(tmp_path / "data", "heldout")
    expected = scene_triples(scene, 32, 2)
    np.testing.assert_array_equal(arrays["views"], expected.views)
    np.testing.assert_array_equal(arrays["depth"], expected.depth)
    # the shard carries the points triangulated from the scene's images, as training reads them
    assert arrays["sfm_depth"].shape == arrays["depth"].shape
    # 48x27 random textures give SIFT nothing it can match across views: no point, and none invented
    # (the triangulation's accuracy on a textured plane is checked above)
    assert not arrays["sfm_depth"].any()
    assert main(["ndn", "shard", str(scene), "--data", str(tmp_path / "bare"), "--working-size", "32",
                 "--multiple", "2", "--no-sfm-points"]) == 0
    assert "sfm_depth" not in load_shards(tmp_path / "bare", "heldout")
