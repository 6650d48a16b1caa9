"""Triangulation with known poses (core/colmap/triangulate.py), shared by the SfM-points scene
and NDN's sparse-SfM baseline: upscaled images with scaled intrinsics, textureless images,
and a reference model it cannot use."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.colmap import Camera, ColmapModel, read_model, write_model
from esgs.core.colmap.triangulate import triangulate_known_poses
from esgs.core.errors import DatasetError
from esgs.core.formats.imageio import read_image, write_png

from .experiments.test_acceptance import _textured_plane_scene


def test_upscaled_images_with_scaled_intrinsics_keep_poses_and_find_the_plane(tmp_path):
    import cv2

    scene, views = _textured_plane_scene(tmp_path / "plane")
    upscaled = tmp_path / "upscaled"
    upscaled.mkdir()
    for name, _, _ in views:
        write_png(upscaled / name, cv2.resize(read_image(scene / "images" / name), None, fx=2.0, fy=2.0,
                                              interpolation=cv2.INTER_CUBIC))
    params = np.array([200.0, 200.0, 120.0, 90.0]) * 2.0
    result = triangulate_known_poses(upscaled, scene / "sparse" / "0", camera_params=params)
    camera = next(iter(result.cameras.values()))
    assert (camera.width, camera.height) == (480, 360)
    np.testing.assert_allclose(camera.params, params)
    xyz = np.array([point.xyz for point in result.points3D.values()])
    assert len(xyz) > 100 and np.median(np.abs(xyz[:, 2])) < 0.01  # the plane z = 0, 3 m away
    for name, rotation, translation in views:
        pose = result.find_image_with_name(name).cam_from_world().matrix()
        np.testing.assert_allclose(pose[:, :3], rotation, atol=1e-9)
        np.testing.assert_allclose(pose[:, 3], translation, atol=1e-9)


def test_textureless_images_give_no_points_and_no_error(tmp_path):
    scene, views = _textured_plane_scene(tmp_path / "plane", views=2, width=64, height=48)
    for name, _, _ in views:
        write_png(scene / "images" / name, np.full((48, 64, 3), 128, np.uint8))
    result = triangulate_known_poses(scene / "images", scene / "sparse" / "0")
    assert result.num_points3D() == 0 and result.num_images() == 2


def test_more_than_one_camera_is_refused(tmp_path):
    scene, _ = _textured_plane_scene(tmp_path / "plane", views=2, width=64, height=48)
    model = read_model(scene)
    model.cameras[2] = Camera(2, "PINHOLE", 64, 48, np.array([50.0, 50.0, 32.0, 24.0]))
    write_model(ColmapModel(model.cameras, model.images, model.points), scene / "sparse" / "0", overwrite=True)
    with pytest.raises(DatasetError, match="supports one camera, the scene has 2"):
        triangulate_known_poses(scene / "images", scene / "sparse" / "0")
