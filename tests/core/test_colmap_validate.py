"""Every validation rule of the COLMAP reader, each with a damaged copy of maupertuis."""
from __future__ import annotations

import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from esgs.core.colmap import check_image_sizes, load_scene, read_model, validate_images, write_model
from esgs.core.errors import DatasetError
from tests.conftest import require_shared


@pytest.fixture
def text_model(tmp_path: Path) -> Path:
    folder = tmp_path / "txt"
    shutil.copytree(require_shared("colmap_maupertuis", "sparse_txt"), folder)
    return folder


@pytest.fixture
def binary_model(tmp_path: Path) -> Path:
    folder = tmp_path / "bin"
    shutil.copytree(require_shared("colmap_maupertuis", "sparse_bin"), folder)
    return folder


def _replace_line(path: Path, starts_with: str, new_line: str) -> None:
    lines = path.read_text().split("\n")
    index = next(i for i, line in enumerate(lines) if line.startswith(starts_with))
    lines[index] = new_line
    path.write_text("\n".join(lines))


def _first_image_line(folder: Path) -> str:
    return next(line for line in (folder / "images.txt").read_text().split("\n") if line and not line.startswith("#"))


def test_unknown_camera_text(text_model: Path) -> None:
    line = _first_image_line(text_model)
    fields = line.split(" ")
    fields[8] = "99"
    _replace_line(text_model / "images.txt", line, " ".join(fields))
    with pytest.raises(DatasetError, match=r"image 4 \(03.jpg\) refers to camera 99, which is not in the cameras file") as info:
        read_model(text_model)
    assert str(text_model) in str(info.value)


def test_unknown_camera_binary(binary_model: Path) -> None:
    data = bytearray((binary_model / "images.bin").read_bytes())
    # u64 count, then u32 id, 7 doubles, u32 camera id.
    struct.pack_into("<I", data, 8 + 4 + 7 * 8, 42)
    (binary_model / "images.bin").write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="refers to camera 42"):
        read_model(binary_model)


def test_no_registered_images(text_model: Path) -> None:
    (text_model / "images.txt").write_text("# no images\n")
    (text_model / "points3D.txt").write_text("")
    with pytest.raises(DatasetError, match="no registered images"):
        read_model(text_model)


def test_track_pointing_past_the_observations(text_model: Path) -> None:
    line = next(line for line in (text_model / "points3D.txt").read_text().split("\n") if line.startswith("708 "))
    fields = line.split(" ")
    fields[9] = "99999"  # 2D index of the first track element
    _replace_line(text_model / "points3D.txt", line, " ".join(fields))
    with pytest.raises(DatasetError, match="3D point 708 is observed as 2D point 99999 of image 2"):
        read_model(text_model)


def test_track_and_observations_disagree(text_model: Path) -> None:
    line = next(line for line in (text_model / "points3D.txt").read_text().split("\n") if line.startswith("708 "))
    fields = line.split(" ")
    fields[9] = str(int(fields[9]) + 1)  # a real 2D point, but not the one that observes 708
    _replace_line(text_model / "points3D.txt", line, " ".join(fields))
    with pytest.raises(DatasetError, match="tracks and image observations disagree"):
        read_model(text_model)


def test_point_observed_in_unknown_image(text_model: Path) -> None:
    line = next(line for line in (text_model / "points3D.txt").read_text().split("\n") if line.startswith("708 "))
    fields = line.split(" ")
    fields[8] = "77"
    _replace_line(text_model / "points3D.txt", line, " ".join(fields))
    with pytest.raises(DatasetError, match="observed in image 77, which is not in the images file"):
        read_model(text_model)


def test_duplicate_image_name(text_model: Path) -> None:
    text = (text_model / "images.txt").read_text()
    (text_model / "images.txt").write_text(text.replace(" 1 01.jpg", " 1 00.jpg"))
    with pytest.raises(DatasetError, match="image name '00.jpg' appears twice"):
        read_model(text_model)


@pytest.mark.parametrize(
    "field, value, message",
    [
        (1, "nan", "is not a number"),
        (1, "1e999", "out of the double range"),
        (0, "4.5", "is not an integer"),
        (1, "0x1p3", "is not a number"),
        (1, "1_0", "is not a number"),
    ],
)
def test_bad_numbers_in_text(text_model: Path, field: int, value: str, message: str) -> None:
    line = _first_image_line(text_model)
    fields = line.split(" ")
    fields[field] = value
    _replace_line(text_model / "images.txt", line, " ".join(fields))
    with pytest.raises(DatasetError, match=message) as info:
        read_model(text_model)
    assert "images.txt" in str(info.value) and "line 5" in str(info.value)


def test_double_spaces_rejected(text_model: Path) -> None:
    text = (text_model / "cameras.txt").read_text()
    (text_model / "cameras.txt").write_text(text.replace("1 SIMPLE_PINHOLE", "1  SIMPLE_PINHOLE"))
    with pytest.raises(DatasetError, match="single spaces"):
        read_model(text_model)


def test_wrong_parameter_count_text(text_model: Path) -> None:
    text = (text_model / "cameras.txt").read_text()
    (text_model / "cameras.txt").write_text(text.replace("SIMPLE_PINHOLE", "PINHOLE"))
    with pytest.raises(DatasetError, match="model PINHOLE takes 4 parameters, got 3"):
        read_model(text_model)


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_truncated_binary_names_file(binary_model: Path, name: str) -> None:
    data = (binary_model / name).read_bytes()
    (binary_model / name).write_bytes(data[: len(data) - 5])
    with pytest.raises(DatasetError, match="truncated") as info:
        read_model(binary_model)
    assert str(binary_model / name) in str(info.value)


def test_trailing_bytes_binary(binary_model: Path) -> None:
    with open(binary_model / "cameras.bin", "ab") as handle:
        handle.write(b"\x00" * 3)
    with pytest.raises(DatasetError, match="3 unexpected bytes after the last record"):
        read_model(binary_model)


def test_huge_count_binary(binary_model: Path) -> None:
    data = bytearray((binary_model / "points3D.bin").read_bytes())
    struct.pack_into("<Q", data, 0, 2**62)
    (binary_model / "points3D.bin").write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="too short"):
        read_model(binary_model)


def test_unknown_model_id_binary(binary_model: Path) -> None:
    data = bytearray((binary_model / "cameras.bin").read_bytes())
    struct.pack_into("<i", data, 8 + 4, 55)
    (binary_model / "cameras.bin").write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="unknown model id 55"):
        read_model(binary_model)


def test_non_finite_pose_binary(binary_model: Path) -> None:
    data = bytearray((binary_model / "images.bin").read_bytes())
    struct.pack_into("<d", data, 8 + 4 + 5 * 8, float("nan"))  # ty of the first image
    (binary_model / "images.bin").write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="non-finite pose"):
        read_model(binary_model)


def test_text_file_that_is_binary(text_model: Path, binary_model: Path) -> None:
    shutil.copyfile(binary_model / "points3D.bin", text_model / "points3D.txt")
    with pytest.raises(DatasetError, match="points3D.txt"):
        read_model(text_model)


def test_write_refuses_inconsistent_model(binary_model: Path, tmp_path: Path) -> None:
    model = read_model(binary_model)
    model.images[1].camera_id = 5
    with pytest.raises(DatasetError, match="refers to camera 5"):
        write_model(model, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["bin"], "no partial folder may be left"


def _scene(tmp_path: Path) -> Path:
    scene = tmp_path / "scene"
    shutil.copytree(require_shared("colmap_maupertuis", "sparse_txt"), scene / "sparse" / "0")
    shutil.copytree(require_shared("colmap_maupertuis", "images"), scene / "images")
    return scene


def test_missing_images_listed(tmp_path: Path) -> None:
    scene = _scene(tmp_path)
    (scene / "images" / "02.jpg").unlink()
    model = read_model(scene)
    with pytest.raises(DatasetError, match="1 of 4 images named in the COLMAP model are missing: 02.jpg"):
        validate_images(model, scene / "images")
    with pytest.raises(DatasetError, match="missing: 02.jpg"):
        load_scene(scene)
    with pytest.raises(DatasetError, match="image folder does not exist"):
        validate_images(model, scene / "nothing")
    model.images[1].name = "/work/shared/data/colmap_maupertuis/images/00.jpg"  # exists, but elsewhere
    with pytest.raises(DatasetError, match="absolute path"):
        validate_images(model, scene / "images")


def test_image_sizes_checked(tmp_path: Path) -> None:
    scene = _scene(tmp_path)
    model = read_model(scene)
    check_image_sizes(model, scene / "images")  # the real images match
    small = cv2.resize(cv2.imread(str(scene / "images" / "01.jpg")), (960, 540))
    cv2.imwrite(str(scene / "images" / "01.jpg"), small)
    with pytest.raises(DatasetError, match=r"01.jpg is 960 x 540, camera 1 says 1919 x 1079"):
        check_image_sizes(model, scene / "images")


def test_unreadable_image_in_size_check(tmp_path: Path) -> None:
    scene = _scene(tmp_path)
    (scene / "images" / "03.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(DatasetError, match="cannot decode image") as info:
        load_scene(scene, check_sizes=True)
    assert "03.jpg" in str(info.value)


def test_model_without_points_is_fine(text_model: Path, tmp_path: Path) -> None:
    """Synthetic scenes may have poses but no triangulated points yet."""
    model = read_model(text_model)
    model.points.clear()
    for image in model.images.values():
        image.point3d_ids = np.full(len(image.point3d_ids), -1, dtype=np.int64)
    again = read_model(write_model(model, tmp_path / "empty_points", binary=True))
    assert len(again.images) == 4 and not again.points


@pytest.mark.parametrize("name", ["../outside.jpg", "/etc/passwd", "a/../../b.jpg", "C:evil.jpg"])
def test_names_leaving_the_image_folder_are_refused(text_model: Path, name: str) -> None:
    text = (text_model / "images.txt").read_text()
    (text_model / "images.txt").write_text(text.replace(" 1 02.jpg", f" 1 {name}"))
    with pytest.raises(DatasetError, match="absolute path|climbs out") as info:
        read_model(text_model)
    assert "images.txt" in str(info.value)


def test_write_refuses_unsafe_or_unstorable_names(binary_model: Path, tmp_path: Path) -> None:
    model = read_model(binary_model)
    model.images[2].name = "../x.jpg"
    with pytest.raises(DatasetError, match="climbs out"):
        write_model(model, tmp_path / "a")
    model.images[2].name = "with space.jpg"
    with pytest.raises(DatasetError, match="spaces"):
        write_model(model, tmp_path / "b", binary=False)
    again = read_model(write_model(model, tmp_path / "c", binary=True))  # binary can hold it
    assert again.images[2].name == "with space.jpg"
