"""Undistortion to PINHOLE against analytic images, pycolmap's projection, COLMAP's own
undistorter and OpenCV's point undistortion."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from esgs.core.colmap import Camera, ColmapModel, Image, Point3D, read_model, write_model
from esgs.core.colmap.geometry import matrix_to_quat_wxyz
from esgs.core.colmap.undistort import (
    undistort_image,
    undistort_model,
    undistort_points,
    undistorted_camera,
    undistortion_maps,
)
from esgs.core.errors import DatasetError
from esgs.core.formats.imageio import read_image, write_png

WIDTH, HEIGHT = 320, 240


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth pattern on the normalised image plane (x/z, y/z): ~1 grey level per pixel."""
    return 127.5 + 90.0 * np.sin(7.0 * x + 1.0) * np.cos(6.0 * y) + 20.0 * x


def pycolmap_camera(camera: Camera) -> pycolmap.Camera:
    return pycolmap.Camera(
        camera_id=camera.camera_id, model=camera.model, width=camera.width, height=camera.height, params=camera.params
    )


def render_distorted(camera: Camera) -> np.ndarray:
    """[H, W] float32 image of ``texture`` seen through the distorted camera (pycolmap's unprojection)."""
    u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    normalized = pycolmap_camera(camera).cam_from_img(np.stack([u.ravel(), v.ravel()], axis=1))
    return texture(normalized[:, 0], normalized[:, 1]).reshape(u.shape).astype(np.float32)


def bilinear(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Sample [H, W] at COLMAP pixel coordinates [N, 2] (centre of pixel (0, 0) at 0.5)."""
    return cv2.remap(
        image, (pixels[:, 0] - 0.5).astype(np.float32)[None], (pixels[:, 1] - 0.5).astype(np.float32)[None], cv2.INTER_LINEAR
    )[0]


CAMERAS = {
    "SIMPLE_RADIAL": [250.0, 160.0, 120.0, -0.18],
    "RADIAL": [250.0, 158.0, 121.0, -0.12, 0.03],
    "OPENCV": [250.0, 255.0, 161.0, 119.0, -0.15, 0.02, 0.001, -0.002],
    "FULL_OPENCV": [250.0, 255.0, 161.0, 119.0, -0.15, 0.02, 0.001, -0.002, 0.001, 0.01, 0.0, 0.001],
    "OPENCV_FISHEYE": [200.0, 201.0, 160.0, 120.0, 0.05, -0.01, 0.002, 0.0],
}


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_undistorted_pixel_matches_distorted_pixel(name: str) -> None:
    """Pixel at the pinhole projection of a 3D point == distorted pixel at pycolmap's projection."""
    camera = Camera(1, name, WIDTH, HEIGHT, np.array(CAMERAS[name]))
    distorted = render_distorted(camera)
    new_camera = undistorted_camera(camera)
    undistorted = undistort_image(distorted, camera, new_camera)
    assert undistorted.shape == (new_camera.height, new_camera.width)

    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-0.45, 0.45, (400, 2)), np.ones((400, 1))], axis=1) * rng.uniform(2, 9, (400, 1))
    at_distorted = np.asarray(pycolmap_camera(camera).img_from_cam(points))
    projected = points @ new_camera.K().T
    at_pinhole = projected[:, :2] / projected[:, 2:]
    inside = (
        np.all((at_pinhole > 2) & (at_pinhole < [new_camera.width - 2, new_camera.height - 2]), axis=1)
        & np.all((at_distorted > 2) & (at_distorted < [WIDTH - 2, HEIGHT - 2]), axis=1)
    )
    assert inside.sum() > 200
    ours = bilinear(undistorted, at_pinhole[inside])
    reference = bilinear(distorted, at_distorted[inside])
    error = np.abs(ours - reference).mean()
    assert error < 0.3
    # The test can fail: ignoring the distortion (sampling the raw image at the pinhole position) is far off.
    naive = bilinear(distorted, (points[inside] @ camera.K().T)[:, :2] / points[inside][:, 2:])
    naive_error = np.abs(naive - reference).mean()
    assert naive_error > 1.0 and naive_error > 10 * error


def test_matches_colmap_undistorter() -> None:
    """Same camera and (up to 8-bit rounding) same pixels as pycolmap.undistort_image."""
    camera = Camera(1, "OPENCV", WIDTH, HEIGHT, np.array(CAMERAS["OPENCV"]))
    distorted = np.clip(np.round(render_distorted(camera)), 0, 255).astype(np.uint8)
    bitmap, colmap_camera = pycolmap.undistort_image(
        pycolmap.UndistortCameraOptions(), pycolmap.Bitmap.from_array(np.repeat(distorted[:, :, None], 3, axis=2)), pycolmap_camera(camera)
    )
    new_camera = undistorted_camera(camera)
    assert (new_camera.width, new_camera.height) == (colmap_camera.width, colmap_camera.height)
    np.testing.assert_allclose(new_camera.params, colmap_camera.params)
    ours = undistort_image(distorted, camera, new_camera).astype(np.float64)
    theirs = bitmap.to_array()[:, :, 0].astype(np.float64)
    assert np.abs(ours - theirs)[2:-2, 2:-2].mean() < 0.6


def test_points_match_opencv() -> None:
    """undistort_points agrees with cv2.undistortPoints (rational model) and cv2.fisheye."""
    rng = np.random.default_rng(1)
    pixels = rng.uniform([20, 20], [WIDTH - 20, HEIGHT - 20], (100, 2))
    for name in ("OPENCV", "FULL_OPENCV"):
        camera = Camera(1, name, WIDTH, HEIGHT, np.array(CAMERAS[name]))
        new_camera = undistorted_camera(camera, keep_size=True)
        reference = cv2.undistortPoints(pixels[:, None], camera.K(), np.array(camera.params[4:]), P=new_camera.K())[:, 0]
        np.testing.assert_allclose(undistort_points(pixels, camera, new_camera), reference, atol=1e-3)
    camera = Camera(1, "OPENCV_FISHEYE", WIDTH, HEIGHT, np.array(CAMERAS["OPENCV_FISHEYE"]))
    new_camera = undistorted_camera(camera, keep_size=True)
    reference = cv2.fisheye.undistortPoints(pixels[:, None], camera.K(), np.array(camera.params[4:]), P=new_camera.K())[:, 0]
    np.testing.assert_allclose(undistort_points(pixels, camera, new_camera), reference, atol=1e-3)


def test_keep_size_and_pinhole_passthrough() -> None:
    camera = Camera(3, "SIMPLE_RADIAL", WIDTH, HEIGHT, np.array(CAMERAS["SIMPLE_RADIAL"]))
    kept = undistorted_camera(camera, keep_size=True)
    assert (kept.model, kept.width, kept.height) == ("PINHOLE", WIDTH, HEIGHT)
    np.testing.assert_array_equal(kept.params, [250.0, 250.0, 160.0, 120.0])
    pinhole = Camera(4, "SIMPLE_PINHOLE", WIDTH, HEIGHT, np.array([300.0, 160.0, 120.0]))
    map_x, map_y = undistortion_maps(pinhole, undistorted_camera(pinhole))
    grid_x, grid_y = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    np.testing.assert_allclose(map_x, grid_x, atol=1e-4)  # identity warp
    np.testing.assert_allclose(map_y, grid_y, atol=1e-4)
    with pytest.raises(DatasetError, match="no pinhole equivalent"):
        undistorted_camera(Camera(5, "EQUIRECTANGULAR", 400, 200, np.array([400.0, 200.0])))


def _synthetic_scene(tmp_path: Path) -> tuple[ColmapModel, Path]:
    """Two views of random 3D points through a SIMPLE_RADIAL camera, images written as PNG."""
    camera = Camera(1, "SIMPLE_RADIAL", WIDTH, HEIGHT, np.array(CAMERAS["SIMPLE_RADIAL"]))
    reference = pycolmap_camera(camera)
    rng = np.random.default_rng(2)
    xyz = rng.uniform([-1.5, -1, 4], [1.5, 1, 6], (30, 3))
    images, observations = {}, {i: [] for i in range(30)}
    images_dir = tmp_path / "images"
    for image_id, angle in ((1, 0.0), (2, 0.1)):
        rotation = cv2.Rodrigues(np.array([0.0, angle, 0.0]))[0]
        translation = np.array([-0.3 * (image_id - 1), 0.0, 0.0])
        camera_points = xyz @ rotation.T + translation
        pixels = np.asarray(reference.img_from_cam(camera_points))
        for index in range(30):
            observations[index].append((image_id, index))
        images[image_id] = Image(
            image_id, f"view_{image_id}.png", 1, matrix_to_quat_wxyz(rotation), translation, pixels, np.arange(30, dtype=np.int64)
        )
        write_png(images_dir / f"view_{image_id}.png", np.clip(render_distorted(camera), 0, 255).astype(np.uint8))
    points = {
        i: Point3D(i, xyz[i], np.array([200, 100, 50], np.uint8), 0.0, np.array([o[0] for o in observations[i]]), np.array([o[1] for o in observations[i]]))
        for i in range(30)
    }
    return ColmapModel({1: camera}, images, points), images_dir


def test_undistort_model_writes_consistent_scene(tmp_path: Path) -> None:
    model, images_dir = _synthetic_scene(tmp_path)
    events = []
    result = undistort_model(model, images_dir, tmp_path / "out", progress=events.append)
    assert [event.step for event in events] == [1, 2]
    again = read_model(tmp_path / "out")
    new_camera = again.cameras[1]
    assert new_camera.model == "PINHOLE" and new_camera.width > WIDTH
    assert (result.cameras[1].width, result.cameras[1].height) == (new_camera.width, new_camera.height)
    np.testing.assert_array_equal(result.cameras[1].params, new_camera.params)
    for image in again.images.values():
        pixels = read_image(tmp_path / "out" / "images" / image.name)
        assert pixels.shape == (new_camera.height, new_camera.width)
        # Observations now follow the pinhole projection of the (unchanged) 3D points.
        xyz = np.stack([again.points[int(i)].xyz for i in image.point3d_ids])
        projected = (xyz @ image.rotation_matrix().T + image.translation) @ new_camera.K().T
        np.testing.assert_allclose(image.points2d, projected[:, :2] / projected[:, 2:], atol=1e-6)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_undistort_model_missing_image_leaves_nothing(tmp_path: Path) -> None:
    model, images_dir = _synthetic_scene(tmp_path)
    (images_dir / "view_2.png").unlink()
    with pytest.raises(DatasetError, match="view_2.png"):
        undistort_model(model, images_dir, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    write_model(model, tmp_path / "model")  # the synthetic model itself is consistent


def test_undistort_model_matches_pycolmap_undistort_images(tmp_path: Path) -> None:
    """Same cameras and (within 8-bit rounding) same pixels as COLMAP's image_undistorter on the CPU."""
    model, images_dir = _synthetic_scene(tmp_path)
    write_model(model, tmp_path / "sparse")
    pycolmap.undistort_images(str(tmp_path / "colmap"), str(tmp_path / "sparse"), str(images_dir))
    ours = undistort_model(model, images_dir, tmp_path / "ours")
    theirs = read_model(tmp_path / "colmap" / "sparse")
    assert (ours.cameras[1].width, ours.cameras[1].height) == (theirs.cameras[1].width, theirs.cameras[1].height)
    np.testing.assert_allclose(ours.cameras[1].params, theirs.cameras[1].params, atol=1e-9)
    for image in ours.images.values():
        np.testing.assert_allclose(image.points2d, theirs.images[image.image_id].points2d, atol=1e-6)
        a = read_image(tmp_path / "ours" / "images" / image.name).astype(np.float64)
        b = read_image(tmp_path / "colmap" / "images" / image.name).astype(np.float64)
        if b.ndim == 3:  # COLMAP writes grey inputs back as RGB
            b = b.mean(axis=2)
        assert np.abs(a - b)[2:-2, 2:-2].mean() < 0.6
