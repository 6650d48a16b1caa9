"""Prior maps: the standard layout read back, checked, resized and converted."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.colmap import read_model
from esgs.core.colmap.geometry import quat_wxyz_to_matrix
from esgs.core.errors import DatasetError
from esgs.core.priors import available_prior_sources, load_prior_maps, write_prior_maps
from esgs.core.priors.sfm import sparse_depth_map, write_sfm_priors
from tests.conftest import require_shared


def _maps(height=8, width=12, seed=0):
    rng = np.random.default_rng(seed)
    depth = rng.uniform(1, 5, (height, width)).astype(np.float32)
    normal = rng.normal(size=(height, width, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    mask = rng.uniform(size=(height, width)) > 0.3
    return depth, normal, mask


def test_round_trip_in_standard_layout(tmp_path):
    depth, normal, mask = _maps()
    write_prior_maps(tmp_path, "gt", "sub/view_001.png", depth=depth, normal=normal, mask=mask)
    assert (tmp_path / "priors/gt/depth/sub/view_001.exr").exists()
    assert (tmp_path / "priors/gt/mask/sub/view_001.png").exists()
    assert available_prior_sources(tmp_path) == ["gt"]
    maps = load_prior_maps(tmp_path, "gt", "sub/view_001.png")
    np.testing.assert_array_equal(maps.depth, depth)
    np.testing.assert_allclose(maps.normal, normal, atol=1e-6)
    np.testing.assert_array_equal(maps.mask, mask)
    assert not maps.relative_depth


def test_relative_flag_world_frame_conversion_and_resize(tmp_path):
    depth, normal, mask = _maps(height=8, width=12)
    from esgs.core.formats.imageio import write_normal_exr

    write_prior_maps(tmp_path, "ndn", "a.png", depth=depth, relative_depth=True)
    rotation = quat_wxyz_to_matrix(np.array([0.9, 0.1, -0.3, 0.2]))
    world_normal = normal @ rotation  # camera = R @ world  ->  world = camera @ R
    write_normal_exr(tmp_path / "priors/ndn/normal/a.exr", world_normal, frame="world")
    with pytest.raises(DatasetError, match="world frame"):
        load_prior_maps(tmp_path, "ndn", "a.png")
    maps = load_prior_maps(tmp_path, "ndn", "a.png", world_to_camera_rotation=rotation)
    assert maps.relative_depth
    np.testing.assert_allclose(maps.normal, normal, atol=1e-5)
    half = load_prior_maps(tmp_path, "ndn", "a.png", size=(6, 4), world_to_camera_rotation=rotation)
    assert half.depth.shape == (4, 6) and half.normal.shape == (4, 6, 3) and half.mask.shape == (4, 6)
    # an integer shrink keeps the nearest valid value of each block (never a blend)
    np.testing.assert_array_equal(half.depth, depth.reshape(4, 2, 6, 2).min(axis=(1, 3)))


def test_sparse_depth_survives_downscaling(tmp_path):
    depth = np.zeros((8, 8), np.float32)
    depth[1, 1] = 3.0
    depth[6, 7] = 4.5
    write_prior_maps(tmp_path, "sfm", "v.png", depth=depth, mask=depth > 0)
    maps = load_prior_maps(tmp_path, "sfm", "v.png", size=(4, 4))
    assert maps.depth[0, 0] == 3.0 and maps.depth[3, 3] == 4.5
    assert maps.mask.sum() == 2


def test_clear_errors(tmp_path):
    with pytest.raises(DatasetError, match="no prior folder for source 'gt'"):
        load_prior_maps(tmp_path, "gt", "x.png")
    depth, normal, mask = _maps()
    write_prior_maps(tmp_path, "gt", "x.png", depth=depth, mask=mask[:4])
    with pytest.raises(DatasetError, match="mask 12x4 does not match") as info:
        load_prior_maps(tmp_path, "gt", "x.png")
    assert "x.png" in str(info.value)
    with pytest.raises(DatasetError, match="no depth, normal or mask prior for image 'y.png'"):
        load_prior_maps(tmp_path, "gt", "y.png")
    write_prior_maps(tmp_path, "gt", "z.png", depth=depth)
    with pytest.raises(DatasetError, match="different aspect ratio"):
        load_prior_maps(tmp_path, "gt", "z.png", size=(12, 12))


def test_sfm_depth_matches_the_points_the_image_observes(tmp_path):
    model = read_model(require_shared("colmap_maupertuis", "sparse_bin"))
    image = model.sorted_images()[0]
    depth = sparse_depth_map(model, image.image_id, max_error_px=1e9, min_track_length=1)
    rotation = image.rotation_matrix()
    linked = np.flatnonzero(image.point3d_ids >= 0)
    assert np.count_nonzero(depth) > 0.9 * len(np.unique(np.floor(image.points2d[linked]).astype(int), axis=0))
    for index in linked[:200]:
        point = model.points[int(image.point3d_ids[index])]
        column, row = np.floor(image.points2d[index]).astype(int)
        z = (rotation @ point.xyz + image.translation)[2]
        assert depth[row, column] <= z + 1e-4  # this point, or a nearer one in the same pixel
    assert write_sfm_priors(tmp_path, model) == len(model.images)
    maps = load_prior_maps(tmp_path, "sfm", image.name)
    assert maps.normal is None and maps.mask.sum() == np.count_nonzero(maps.depth)


def test_priors_command_writes_sfm_maps(tmp_path):
    import shutil
    import subprocess
    import sys

    data = require_shared("colmap_maupertuis")
    (tmp_path / "sparse").mkdir()
    shutil.copytree(data / "sparse_bin", tmp_path / "sparse" / "0")
    shutil.copytree(data / "images", tmp_path / "images")
    result = subprocess.run([sys.executable, "-m", "esgs.core", "priors", str(tmp_path), "--method", "sfm"],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in (tmp_path / "priors/sfm/depth").iterdir()) == ["00.exr", "01.exr", "02.exr", "03.exr"]
    missing = subprocess.run([sys.executable, "-m", "esgs.core", "priors", str(tmp_path / "nope")],
                             capture_output=True, text=True)
    assert missing.returncode == 1 and "Traceback" not in missing.stderr  # bad data: 1 (README, exit status)


def test_mask_kind_says_whether_unmasked_pixels_are_sky(tmp_path):
    depth, normal, mask = _maps()
    write_prior_maps(tmp_path, "ndn", "a.png", depth=depth, normal=normal, mask=mask, mask_kind="surface")
    write_prior_maps(tmp_path, "labels", "a.png", depth=depth, normal=normal, mask=mask)
    sky = load_prior_maps(tmp_path, "ndn", "a.png", size=(6, 4)).sky
    assert sky is not None and sky.shape == (4, 6)
    np.testing.assert_array_equal(sky, ~load_prior_maps(tmp_path, "ndn", "a.png", size=(6, 4)).mask)
    assert load_prior_maps(tmp_path, "labels", "a.png").sky is None  # holes in coverage are not sky
    with pytest.raises(ValueError, match="mask_kind"):
        write_prior_maps(tmp_path, "ndn", "b.png", depth=depth, mask=mask, mask_kind="sky")


def test_files_without_mask_kind_follow_their_source(tmp_path):
    from esgs.core.formats.imageio import write_depth_exr, write_png

    depth, _, mask = _maps()
    for source in ("gt", "sfm"):
        write_depth_exr(tmp_path / "priors" / source / "depth" / "a.exr", depth)
        write_png(tmp_path / "priors" / source / "mask" / "a.png", np.where(mask, 255, 0).astype(np.uint8))
    np.testing.assert_array_equal(load_prior_maps(tmp_path, "gt", "a.png").sky, ~mask)
    assert load_prior_maps(tmp_path, "sfm", "a.png").sky is None
    write_depth_exr(tmp_path / "priors" / "gt" / "depth" / "b.exr", depth, metadata={"mask_kind": "maybe"})
    with pytest.raises(DatasetError, match="mask_kind") as error:
        load_prior_maps(tmp_path, "gt", "b.png")
    assert "b.exr" in str(error.value)


def test_a_folder_of_masks_alone_reads_as_sky_masks(tmp_path):
    depth, normal, mask = _maps()
    write_prior_maps(tmp_path, "gt", "x.png", mask=mask)
    maps = load_prior_maps(tmp_path, "gt", "x.png")
    assert maps.depth is None and maps.normal is None
    np.testing.assert_array_equal(maps.mask, mask)
    np.testing.assert_array_equal(maps.sky, ~mask)  # gt masks' zeros are sky
    half = load_prior_maps(tmp_path, "gt", "x.png", size=(mask.shape[1] // 2, mask.shape[0] // 2))
    assert half.mask.shape == (mask.shape[0] // 2, mask.shape[1] // 2)
