"""Fuzzing the COLMAP readers: damaged maupertuis files give a model or a DatasetError.

Anything else (another exception type, or pycolmap aborting the process) fails the run.
Each example writes a damaged copy of one file beside intact copies of the other two.
"""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from esgs.core.colmap import ColmapModel, read_model
from esgs.core.errors import DatasetError
from tests.conftest import require_shared
from tests.core.test_colmap_io import assert_models_equal

FILES = {
    "bin": ["cameras.bin", "images.bin", "points3D.bin"],
    "txt": ["cameras.txt", "images.txt", "points3D.txt"],
}
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)


def _source(extension: str) -> Path:
    return require_shared("colmap_maupertuis", "sparse_bin" if extension == "bin" else "sparse_txt")


def _read_damaged(extension: str, name: str, data: bytes) -> ColmapModel | None:
    """Read the model with ``name`` replaced by ``data``; None when a DatasetError was raised."""
    source = _source(extension)
    with tempfile.TemporaryDirectory(prefix="esgs_fuzz_") as folder:
        for other in FILES[extension]:
            if other != name:
                shutil.copyfile(source / other, Path(folder) / other)
        (Path(folder) / name).write_bytes(data)
        try:
            model = read_model(folder, use_pycolmap=True)
        except DatasetError as error:
            assert str(error), "a DatasetError must say what is wrong"
            return None
        # Whatever got through, both readers must see the same model.
        assert_models_equal(model, read_model(folder, use_pycolmap=False))
    assert isinstance(model, ColmapModel) and model.images
    return model


# Positions are drawn as fractions so one strategy serves files of any size; half the draws
# land in the first kilobyte where headers, ids and names live.
_position = st.one_of(st.floats(0.0, 1.0, exclude_max=True), st.integers(0, 1023))


def _offset(position: float | int, size: int) -> int:
    return int(position * size) if isinstance(position, float) else min(position, size - 1)


@pytest.mark.parametrize("extension", ["bin", "txt"])
@settings(FUZZ)
@given(name_index=st.integers(0, 2), cut=st.floats(0.0, 1.0, exclude_max=True))
def test_truncated_files(extension: str, name_index: int, cut: float) -> None:
    name = FILES[extension][name_index]
    data = (_source(extension) / name).read_bytes()
    length = int(cut * len(data))
    model = _read_damaged(extension, name, data[:length])
    if extension == "bin":
        # Every binary record ends exactly at the file's end: a shorter file cannot be read.
        assert model is None


@pytest.mark.parametrize("extension", ["bin", "txt"])
@settings(FUZZ)
@given(
    name_index=st.integers(0, 2),
    edits=st.lists(st.tuples(_position, st.integers(0, 255)), min_size=1, max_size=8),
)
def test_byte_mutations(extension: str, name_index: int, edits: list[tuple[float | int, int]]) -> None:
    name = FILES[extension][name_index]
    data = bytearray((_source(extension) / name).read_bytes())
    for position, value in edits:
        data[_offset(position, len(data))] = value
    _read_damaged(extension, name, bytes(data))


@settings(FUZZ, max_examples=30)  # most edits keep the model valid: each example reads it twice
@given(
    name_index=st.integers(0, 2),
    position=_position,
    insert=st.sampled_from([b"", b" ", b"  ", b"\n", b"-", b"1", b"e9", b"nan", b"#", b"\t", b"\xff", b"\x00", b".5"]),
    delete=st.integers(0, 4),
)
def test_text_insertions_and_deletions(name_index: int, position: float | int, insert: bytes, delete: int) -> None:
    name = FILES["txt"][name_index]
    data = (_source("txt") / name).read_bytes()
    offset = _offset(position, len(data))
    _read_damaged("txt", name, data[:offset] + insert + data[offset + delete :])


@pytest.mark.parametrize("extension", ["bin", "txt"])
@pytest.mark.parametrize("name_index", [0, 1, 2])
def test_empty_files(extension: str, name_index: int) -> None:
    name = FILES[extension][name_index]
    assert _read_damaged(extension, name, b"") is None
