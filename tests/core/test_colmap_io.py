"""COLMAP model reading/writing against the real maupertuis model and pycolmap itself."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from esgs.core.colmap import (
    ColmapModel,
    find_model_dir,
    load_scene,
    parse_model,
    read_model,
    write_model,
)
from esgs.core.errors import ConfigError, DatasetError
from tests.conftest import require_shared


@pytest.fixture
def maupertuis() -> Path:
    return require_shared("colmap_maupertuis")


def assert_models_equal(a: ColmapModel, b: ColmapModel, *, atol: float = 0.0) -> None:
    """Same ids, names, cameras, poses, observations, points and tracks."""
    assert sorted(a.cameras) == sorted(b.cameras)
    for camera_id, camera in a.cameras.items():
        other = b.cameras[camera_id]
        assert (camera.model, camera.width, camera.height) == (other.model, other.width, other.height)
        np.testing.assert_allclose(camera.params, other.params, rtol=0, atol=atol)
    assert sorted(a.images) == sorted(b.images)
    for image_id, image in a.images.items():
        other = b.images[image_id]
        assert (image.name, image.camera_id) == (other.name, other.camera_id)
        # q and -q are the same rotation; compare the matrices.
        np.testing.assert_allclose(image.rotation_matrix(), other.rotation_matrix(), rtol=0, atol=max(atol, 1e-12))
        np.testing.assert_allclose(image.translation, other.translation, rtol=0, atol=atol)
        np.testing.assert_allclose(image.points2d, other.points2d, rtol=0, atol=atol)
        np.testing.assert_array_equal(image.point3d_ids, other.point3d_ids)
    assert sorted(a.points) == sorted(b.points)
    for point_id, point in a.points.items():
        other = b.points[point_id]
        np.testing.assert_allclose(point.xyz, other.xyz, rtol=0, atol=atol)
        np.testing.assert_array_equal(point.rgb, other.rgb)
        assert point.error == pytest.approx(other.error, abs=atol)
        np.testing.assert_array_equal(point.track_image_ids, other.track_image_ids)
        np.testing.assert_array_equal(point.track_point2d_idxs, other.track_point2d_idxs)


@pytest.mark.parametrize("folder", ["sparse_bin", "sparse_txt"])
def test_read_matches_readme_counts(maupertuis: Path, folder: str) -> None:
    model = read_model(maupertuis / folder)
    assert len(model.cameras) == 1 and len(model.images) == 4 and len(model.points) == 1039
    assert sum(point.track_length for point in model.points.values()) == 3355
    camera = model.cameras[1]
    assert camera.model == "SIMPLE_PINHOLE" and (camera.width, camera.height) == (1919, 1079)
    assert camera.intrinsics() == pytest.approx((1847.53, 1847.53, 959.5, 539.5))
    assert [image.name for image in model.sorted_images()] == ["00.jpg", "01.jpg", "02.jpg", "03.jpg"]
    assert model.source == str(maupertuis / folder)


def test_binary_and_text_agree(maupertuis: Path) -> None:
    assert_models_equal(read_model(maupertuis / "sparse_bin"), read_model(maupertuis / "sparse_txt"))


@pytest.mark.parametrize("folder", ["sparse_bin", "sparse_txt"])
def test_own_parser_agrees_with_pycolmap(maupertuis: Path, folder: str) -> None:
    reference = read_model(maupertuis / folder, use_pycolmap=True)
    assert_models_equal(parse_model(maupertuis / folder), reference)
    assert_models_equal(read_model(maupertuis / folder), reference)  # the default reads once


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("folder", ["sparse_bin", "sparse_txt"])
def test_round_trip(maupertuis: Path, tmp_path: Path, folder: str, binary: bool) -> None:
    model = read_model(maupertuis / folder)
    out = write_model(model, tmp_path / "model", binary=binary)
    extension = "bin" if binary else "txt"
    assert {f"{name}.{extension}" for name in ("cameras", "images", "points3D")} <= {p.name for p in out.iterdir()}
    again = read_model(out)
    # Binary keeps doubles exactly; COLMAP's text writer prints 17 significant digits... or fewer.
    assert_models_equal(model, again, atol=0.0 if binary else 1e-9)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temporary folders left behind"


def test_geometry_matches_pycolmap(maupertuis: Path) -> None:
    """Camera centres and reprojections through our K/pose equal pycolmap's own."""
    model = read_model(maupertuis / "sparse_bin")
    reconstruction = pycolmap.Reconstruction(str(maupertuis / "sparse_bin"))
    for image_id, image in model.images.items():
        reference = reconstruction.images[image_id]
        # The files hold 6-digit quaternions (|q| - 1 ~ 4e-7); we normalise, pycolmap's
        # inverse pose does not, hence the small tolerances.
        np.testing.assert_allclose(image.camera_center(), reference.projection_center(), atol=2e-5)
        camera = model.cameras[image.camera_id]
        observed = np.flatnonzero(image.point3d_ids >= 0)
        xyz = np.stack([model.points[int(i)].xyz for i in image.point3d_ids[observed]])
        camera_points = xyz @ image.rotation_matrix().T + image.translation
        projected = camera_points @ camera.K().T
        ours = projected[:, :2] / projected[:, 2:]
        theirs = np.stack([reference.project_point(point) for point in xyz])
        np.testing.assert_allclose(ours, theirs, atol=2e-3)
        # And the reprojection error against the stored keypoints is COLMAP's (sub-pixel).
        assert np.median(np.linalg.norm(ours - image.points2d[observed], axis=1)) < 1.0


def test_scene_folder_with_sparse_0(maupertuis: Path, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    shutil.copytree(maupertuis / "sparse_bin", scene / "sparse" / "0")
    shutil.copytree(maupertuis / "images", scene / "images")
    assert find_model_dir(scene) == (scene / "sparse" / "0", "bin")
    model, images_dir = load_scene(scene, check_sizes=True)
    assert images_dir == scene / "images" and len(model.images) == 4


def test_write_refuses_non_empty_folder_without_overwrite(maupertuis: Path, tmp_path: Path) -> None:
    model = read_model(maupertuis / "sparse_bin")
    target = tmp_path / "model"
    target.mkdir()  # empty folders are fine
    write_model(model, target)
    with pytest.raises(ConfigError):
        write_model(model, target)
    write_model(model, target, binary=False, overwrite=True)
    assert (target / "cameras.txt").is_file() and not (target / "cameras.bin").exists()


def test_missing_files_are_named(maupertuis: Path, tmp_path: Path) -> None:
    shutil.copytree(maupertuis / "sparse_bin", tmp_path / "m")
    (tmp_path / "m" / "points3D.bin").unlink()
    with pytest.raises(DatasetError, match="points3D.bin missing"):
        read_model(tmp_path / "m")
    with pytest.raises(DatasetError, match="no COLMAP model found"):
        read_model(tmp_path)
    with pytest.raises(DatasetError, match="does not exist"):
        read_model(tmp_path / "nothing")


def random_model(seed: int = 0) -> ColmapModel:
    """A consistent model with full-precision doubles, three camera models, shared points."""
    from esgs.core.colmap import Camera, Image, Point3D

    rng = np.random.default_rng(seed)
    cameras = {
        1: Camera(1, "OPENCV", 640, 480, rng.uniform(0.01, 500, 8)),
        4: Camera(4, "SIMPLE_RADIAL", 800, 600, rng.uniform(0.01, 500, 4)),
        9: Camera(9, "FULL_OPENCV", 1024, 768, rng.uniform(0.01, 500, 12)),
    }
    images, tracks = {}, {}
    for image_id, camera_id in ((3, 1), (5, 4), (8, 9), (11, 4)):
        ids = np.full(40, -1, dtype=np.int64)
        for index in rng.choice(40, 25, replace=False):
            point_id = int(rng.integers(1, 30)) * 7
            if any(image == image_id for image, _ in tracks.get(point_id, [])):
                continue  # one observation per image and point, as COLMAP keeps it
            ids[index] = point_id
            tracks.setdefault(point_id, []).append((image_id, int(index)))
        quat = rng.normal(size=4)
        images[image_id] = Image(image_id, f"dir/img_{image_id}.png", camera_id, quat / np.linalg.norm(quat) * np.sign(quat[0]),
                                 rng.normal(size=3), rng.uniform(0, 600, (40, 2)), ids)
    points = {
        point_id: Point3D(point_id, rng.normal(size=3), rng.integers(0, 256, 3).astype(np.uint8), float(rng.uniform()),
                          np.array([t[0] for t in track]), np.array([t[1] for t in track]))
        for point_id, track in tracks.items()
    }
    return ColmapModel(cameras, images, points)


@pytest.mark.parametrize("binary", [True, False])
def test_round_trip_synthetic_full_precision(tmp_path: Path, binary: bool) -> None:
    model = random_model()
    write_model(model, tmp_path / "m", binary=binary)
    again = read_model(tmp_path / "m")
    # COLMAP prints 17 significant digits in text: doubles survive exactly there too;
    # quaternions only to 1 ulp (pycolmap normalises them).
    assert_models_equal(model, again, atol=0.0)
    for image_id, image in model.images.items():
        np.testing.assert_allclose(again.images[image_id].quat_wxyz, image.quat_wxyz, rtol=0, atol=1e-15)
    assert_models_equal(read_model(tmp_path / "m", use_pycolmap=False), again)


def test_windows_line_endings(maupertuis: Path, tmp_path: Path) -> None:
    for name in ("cameras", "images", "points3D"):
        text = (maupertuis / "sparse_txt" / f"{name}.txt").read_bytes()
        (tmp_path / f"{name}.txt").write_bytes(text.replace(b"\n", b"\r\n"))
    assert_models_equal(read_model(tmp_path), read_model(maupertuis / "sparse_txt"))
