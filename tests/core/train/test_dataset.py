"""Scene loading: split, extent, resolution, undistortion, masks; initial Gaussians."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from esgs.core.errors import DatasetError
from esgs.core.train.dataset import load_scene_data, scene_extent, split_indices, target_size
from esgs.core.train.gaussians import SH_C0, GaussianModel


def test_split_every_eighth_sorted_image():
    train, test = split_indices(20, 8)
    assert test == [0, 8, 16] and len(train) == 17 and not set(train) & set(test)
    assert split_indices(5, 0) == ([0, 1, 2, 3, 4], [])


def test_scene_extent_is_3dgs_radius():
    centers = np.array([[0.0, 0, 0], [2.0, 0, 0], [1.0, 3.0, 0]])
    extent, mean = scene_extent(centers)
    assert np.allclose(mean, [1.0, 1.0, 0.0])
    assert extent == pytest.approx(1.1 * 2.0)  # the farthest centre, (1, 3, 0), is 2 from the mean


def test_load_scene_split_and_intrinsics(tiny_scene):
    full = load_scene_data(tiny_scene)
    assert [v.name for v in full.test] == ["view_000.png", "view_008.png"] and len(full.train) == 8
    half = load_scene_data(tiny_scene, resolution=2)
    view, reference = half.train[0], full.train[0]
    assert (view.width, view.height) == (16, 12) and view.image.shape == (12, 16, 3)
    assert torch.allclose(view.K[:2], reference.K[:2] / 2)
    # a half-size image is the 2x2 box average of the full one
    box = reference.image.float().reshape(12, 2, 16, 2, 3).mean(dim=(1, 3))
    assert (view.image.float() - box).abs().max() <= 1.0
    assert target_size(1920, 1080, 1, 480) == (480, 270)
    assert half.extent == pytest.approx(full.extent)
    assert len(full.points_xyz) == 150 and full.points_rgb.max() <= 1.0


def test_distorted_camera_is_undistorted(tiny_scene, tmp_path):
    """A SIMPLE_RADIAL camera with k = 0 goes through undistortion: COLMAP crops to a
    slightly smaller PINHOLE camera with the same focal length; pixels follow their rays."""
    import cv2

    from esgs.core.colmap.io import read_model, write_model

    scene = tmp_path / "radial"
    shutil.copytree(tiny_scene / "images", scene / "images")
    model = read_model(tiny_scene)
    camera = model.cameras[1]
    fx, fy, cx, cy = camera.intrinsics()
    model.cameras[1] = type(camera)(1, "SIMPLE_RADIAL", camera.width, camera.height, np.array([fx, cx, cy, 0.0]))
    write_model(model, scene / "sparse" / "0")
    view = load_scene_data(scene).train[0]
    reference = load_scene_data(tiny_scene).train[0]
    assert abs(view.width - reference.width) <= 2 and abs(view.height - reference.height) <= 2
    assert float(view.K[0, 0]) == pytest.approx(fx, rel=1e-3) and float(view.K[1, 1]) == pytest.approx(fy, rel=1e-3)
    new_cx, new_cy = float(view.K[0, 2]), float(view.K[1, 2])
    # with k = 0 the warp is a pure shift: new pixel centre u + 0.5 sees old coordinate u + 0.5 - new_cx + cx
    map_x = (np.arange(view.width, dtype=np.float32) - new_cx + cx)[None].repeat(view.height, 0)
    map_y = (np.arange(view.height, dtype=np.float32) - new_cy + cy)[:, None].repeat(view.width, 1)
    expected = cv2.remap(reference.image.numpy(), map_x, map_y, cv2.INTER_LINEAR)
    assert np.abs(view.image.numpy().astype(int) - expected.astype(int))[1:-1, 1:-1].max() <= 1


def test_missing_image_and_bad_mask_source(tiny_scene, tmp_path):
    scene = tmp_path / "broken"
    shutil.copytree(tiny_scene, scene)
    (scene / "images" / "view_003.png").unlink()
    with pytest.raises(DatasetError, match="view_003.png"):
        load_scene_data(scene)
    with pytest.raises(DatasetError, match="no mask folder"):
        load_scene_data(tiny_scene, mask_source="ndn")
    with pytest.raises(DatasetError, match="scene folder not found"):
        load_scene_data(tmp_path / "nothing")


def test_mask_is_downscaled_by_majority(tiny_scene, tmp_path):
    from esgs.core.formats.imageio import write_png

    scene = tmp_path / "masked"
    shutil.copytree(tiny_scene, scene)
    folder = scene / "priors" / "labels" / "mask"
    folder.mkdir(parents=True)
    mask = np.zeros((24, 32), np.uint8)
    mask[:, :16] = 255  # left half valid
    mask[0, 16] = 255   # one stray pixel in a 2x2 block: not a majority
    for image in (scene / "images").iterdir():
        write_png(folder / f"{image.stem}.png", mask)
    data = load_scene_data(scene, resolution=2)
    assert data.mask_source == "labels"
    loaded = data.train[0].mask[:, :, 0]
    assert loaded.shape == (12, 16) and loaded[:, :8].all() and not loaded[:, 8:].any()


def test_from_points_scale_colour_and_opacity():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, size=(50, 3))
    rgb = rng.uniform(0, 1, size=(50, 3))
    model = GaussianModel.from_points(xyz, rgb, init_opacity=0.1)
    distances = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    np.fill_diagonal(distances, np.inf)
    expected = np.sort(distances, axis=1)[:, :3].mean(axis=1)
    assert np.allclose(model.scales().detach().numpy(), expected[:, None].repeat(3, 1), rtol=1e-5)
    assert torch.allclose(model.opacities(), torch.full((50,), 0.1))
    assert np.allclose((model.params["sh_dc"][:, 0].detach().numpy() * SH_C0 + 0.5), rgb, atol=1e-6)
    assert model.params["sh_rest"].shape == (50, 15, 3) and not model.params["sh_rest"].any()
    assert torch.equal(model.unit_quats(), torch.tensor([[1.0, 0, 0, 0]]).repeat(50, 1))


def test_auto_mask_never_takes_sparse_sfm_masks(tmp_path):
    from esgs.core.train.dataset import find_mask_source

    (tmp_path / "priors" / "sfm" / "mask").mkdir(parents=True)
    assert find_mask_source(tmp_path, "auto") is None
    (tmp_path / "priors" / "gt" / "mask").mkdir(parents=True)
    assert find_mask_source(tmp_path, "auto") == "gt"
    assert find_mask_source(tmp_path, "sfm") == "sfm"  # still possible when asked for by name


def test_auto_mask_prefers_a_source_that_marks_the_sky_over_a_coverage_mask(tmp_path):
    """Without gt, ndn's masks come before the labels' once its sky maps mark some sky (the
    trainer's sky terms need it); without any sky marked, the order is gt, labels, ndn."""
    from esgs.core.priors import write_prior_maps
    from esgs.core.train.dataset import find_mask_source

    surface = np.ones((6, 8), bool)
    write_prior_maps(tmp_path, "labels", "a.png", depth=np.ones((6, 8), np.float32), mask=surface)
    write_prior_maps(tmp_path, "ndn", "a.png", depth=np.ones((6, 8), np.float32), mask=surface,
                     relative_depth=True, units="relative", mask_kind="surface", sky=np.zeros((6, 8), bool))
    assert find_mask_source(tmp_path, "auto") == "labels"  # ndn's sky maps mark nothing
    sky = np.zeros((6, 8), bool)
    sky[0, :] = True
    write_prior_maps(tmp_path, "ndn", "b.png", depth=np.ones((6, 8), np.float32), mask=~sky,
                     relative_depth=True, units="relative", mask_kind="surface", sky=sky)
    assert find_mask_source(tmp_path, "auto") == "ndn"
    write_prior_maps(tmp_path, "gt", "a.png", depth=np.ones((6, 8), np.float32), mask=surface)
    assert find_mask_source(tmp_path, "auto") == "gt"  # the scene's exact masks first, as before
    assert find_mask_source(tmp_path, "labels") == "labels"
