"""Image and EXR IO: exact round trips, colour order, metadata, and damaged files."""
from __future__ import annotations

import tempfile
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from esgs.core.errors import DatasetError, ESGSError, FormatError
from esgs.core.formats.imageio import (
    read_depth_exr,
    read_exr,
    read_image,
    read_normal_exr,
    write_depth_exr,
    write_exr,
    write_normal_exr,
    write_png,
)
from tests.conftest import require_shared


def leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if p.name.startswith(".")]


# --------------------------------------------------------------------------------------
# 8-bit images


def test_png_round_trip_rgb_and_colour_order(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (17, 23, 3), dtype=np.uint8)
    rgb[0, 0] = [255, 0, 0]  # pure red in RGB order
    write_png(tmp_path / "a.png", rgb)
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), rgb)
    # Independent check of the channel order: OpenCV itself reads BGR.
    assert cv2.imread(str(tmp_path / "a.png"))[0, 0].tolist() == [0, 0, 255]
    assert leftovers(tmp_path) == []


def test_png_grey_rgba_and_16_bit(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    grey = rng.integers(0, 256, (9, 11), dtype=np.uint8)
    write_png(tmp_path / "grey.png", grey)
    np.testing.assert_array_equal(read_image(tmp_path / "grey.png"), grey)
    rgba = rng.integers(0, 256, (9, 11, 4), dtype=np.uint8)
    write_png(tmp_path / "rgba.png", rgba)
    np.testing.assert_array_equal(read_image(tmp_path / "rgba.png"), rgba[:, :, :3])
    deep = (rng.integers(0, 256, (9, 11, 3)) * 257).astype(np.uint16)
    write_png(tmp_path / "deep.png", deep)
    assert cv2.imread(str(tmp_path / "deep.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    np.testing.assert_array_equal(read_image(tmp_path / "deep.png"), (deep // 257).astype(np.uint8))


def test_read_real_jpeg() -> None:
    image = read_image(require_shared("colmap_maupertuis", "images", "00.jpg"))
    assert image.shape == (1079, 1919, 3) and image.dtype == np.uint8
    reference = cv2.imread(str(require_shared("colmap_maupertuis", "images", "00.jpg")))[:, :, ::-1]
    np.testing.assert_array_equal(image, reference)


def test_unreadable_images(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="cannot read image") as info:
        read_image(tmp_path / "missing.png")
    assert "missing.png" in str(info.value)
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(DatasetError, match="empty"):
        read_image(tmp_path / "empty.png")
    (tmp_path / "junk.jpg").write_bytes(b"\xff\xd8\xff garbage" * 10)
    with pytest.raises(DatasetError, match="cannot decode"):
        read_image(tmp_path / "junk.jpg")
    write_png(tmp_path / "ok.png", np.zeros((40, 40, 3), np.uint8))
    data = (tmp_path / "ok.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 3])
    with pytest.raises(DatasetError):
        read_image(tmp_path / "cut.png")


def test_write_png_rejects_bad_arrays_and_leaves_nothing(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="uint8 or uint16"):
        write_png(tmp_path / "a.png", np.zeros((4, 4), np.float32))
    with pytest.raises(FormatError, match="shape"):
        write_png(tmp_path / "a.png", np.zeros((4, 4, 2), np.uint8))
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------
# EXR


def special_floats(shape: tuple[int, int], seed: int) -> np.ndarray:
    """Random float32 with the awkward values too: inf, nan, subnormals, -0."""
    values = np.random.default_rng(seed).normal(0, 100, shape).astype(np.float32)
    flat = values.reshape(-1)
    flat[:5] = [np.inf, -np.inf, np.nan, 1e-42, -0.0]
    return values


def test_exr_round_trip_is_bit_exact_with_metadata(tmp_path: Path) -> None:
    channels = {"A": special_floats((13, 29), 0), "B": special_floats((13, 29), 1), "depth.V": special_floats((13, 29), 2)}
    metadata = {"frame": "camera_opencv", "units": "m", "note": "ünïcode ok"}
    write_exr(tmp_path / "x.exr", channels, metadata)
    read_channels, read_metadata = read_exr(tmp_path / "x.exr")
    assert sorted(read_channels) == sorted(channels)
    for name, values in channels.items():
        assert read_channels[name].dtype == np.float32
        np.testing.assert_array_equal(read_channels[name].view(np.uint32), values.view(np.uint32))
    assert read_metadata == metadata
    assert leftovers(tmp_path) == []


def test_depth_and_normal_helpers(tmp_path: Path) -> None:
    depth = np.abs(special_floats((8, 12), 3))
    write_depth_exr(tmp_path / "d.exr", depth, metadata={"source": "gt"})
    read_depth, metadata = read_depth_exr(tmp_path / "d.exr")
    np.testing.assert_array_equal(read_depth.view(np.uint32), depth.view(np.uint32))
    assert metadata == {"quantity": "depth_z", "units": "m", "frame": "camera_opencv", "source": "gt"}
    # The file itself holds one channel named Z (readable by other tools).
    assert list(OpenEXR.File(str(tmp_path / "d.exr"), separate_channels=True).channels()) == ["Z"]

    normals = np.random.default_rng(4).normal(size=(8, 12, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    write_normal_exr(tmp_path / "n.exr", normals, frame="world")
    read_normals, metadata = read_normal_exr(tmp_path / "n.exr")
    np.testing.assert_array_equal(read_normals, normals)
    assert metadata["frame"] == "world"
    assert sorted(OpenEXR.File(str(tmp_path / "n.exr"), separate_channels=True).channels()) == ["X", "Y", "Z"]


def test_blender_style_single_channel_depth(tmp_path: Path) -> None:
    """Blender's File Output node writes depth as one half/float channel named V."""
    values = np.linspace(0, 10, 35, dtype=np.float16).reshape(5, 7)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"V": values}).write(str(tmp_path / "b.exr"))
    depth, _ = read_depth_exr(tmp_path / "b.exr")
    assert depth.dtype == np.float32
    np.testing.assert_array_equal(depth, values.astype(np.float32))
    write_exr(tmp_path / "two.exr", {"P": values, "Q": values})
    with pytest.raises(DatasetError, match="no depth channel 'Z'"):
        read_depth_exr(tmp_path / "two.exr")
    with pytest.raises(DatasetError, match="no normal channels"):
        read_normal_exr(tmp_path / "two.exr")


def test_exr_write_errors(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="at least one channel"):
        write_exr(tmp_path / "e.exr", {})
    with pytest.raises(FormatError, match="other channels"):
        write_exr(tmp_path / "e.exr", {"A": np.zeros((2, 3)), "B": np.zeros((3, 2))})
    with pytest.raises(ESGSError, match="reserved"):
        write_exr(tmp_path / "e.exr", {"A": np.zeros((2, 3))}, {"compression": "none"})
    with pytest.raises(ESGSError, match="must be a string"):
        write_exr(tmp_path / "e.exr", {"A": np.zeros((2, 3))}, {"scale": 2.0})  # type: ignore[dict-item]
    with pytest.raises(FormatError, match=r"\[H, W, 3\]"):
        write_normal_exr(tmp_path / "e.exr", np.zeros((2, 3)))
    assert list(tmp_path.iterdir()) == []


def test_corrupt_exr(tmp_path: Path) -> None:
    write_depth_exr(tmp_path / "d.exr", np.ones((40, 30), np.float32))
    data = (tmp_path / "d.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) - 20])
    with pytest.raises(DatasetError, match="cut.exr: cannot read EXR"):
        read_exr(tmp_path / "cut.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all")
    with pytest.raises(DatasetError, match="junk.exr"):
        read_depth_exr(tmp_path / "junk.exr")
    with pytest.raises(DatasetError, match="does not exist"):
        read_exr(tmp_path / "none.exr")


_SOURCE_EXR: bytes | None = None


def _source_exr() -> bytes:
    global _SOURCE_EXR
    if _SOURCE_EXR is None:
        with tempfile.TemporaryDirectory() as folder:
            # A smooth map compresses, so its chunks are ZIP streams (checked on decode).
            y, x = np.mgrid[0:48, 0:40].astype(np.float32)
            write_normal_exr(Path(folder) / "n.exr", np.stack([x, y, x + y], axis=-1), metadata={"frame": "world"})
            _SOURCE_EXR = (Path(folder) / "n.exr").read_bytes()
    return _SOURCE_EXR


@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(
    cut=st.one_of(st.none(), st.floats(0.0, 1.0, exclude_max=True)),
    edits=st.lists(st.tuples(st.floats(0.0, 1.0, exclude_max=True), st.integers(0, 255)), max_size=6),
)
def test_exr_fuzz_gives_data_or_dataset_error(cut: float | None, edits: list[tuple[float, int]]) -> None:
    data = bytearray(_source_exr())
    for position, value in edits:
        data[int(position * len(data))] = value
    if cut is not None:
        data = data[: int(cut * len(data))]
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "f.exr"
        path.write_bytes(bytes(data))
        try:
            channels, metadata = read_exr(path)
        except DatasetError:
            return
    assert channels and all(array.ndim == 2 for array in channels.values())
    assert all(isinstance(value, str) for value in metadata.values())
