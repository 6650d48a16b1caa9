"""Our camera-model table and pinhole_part against pycolmap's own definitions."""
from __future__ import annotations

import zlib

import numpy as np
import pycolmap
import pytest

from esgs.core.colmap import CAMERA_MODELS, Camera, model_info, pinhole_part
from esgs.core.errors import DatasetError

PYCOLMAP_MODELS = [name for name in pycolmap.CameraModelId.__members__ if name != "INVALID"]


def test_table_covers_every_pycolmap_model() -> None:
    assert sorted(CAMERA_MODELS) == sorted(PYCOLMAP_MODELS)


@pytest.mark.parametrize("name", PYCOLMAP_MODELS)
def test_model_matches_pycolmap(name: str) -> None:
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    reference = pycolmap.Camera.create_from_model_name(7, name, 500.0, 640, 480)
    params = np.asarray(reference.params, dtype=np.float64) * rng.uniform(0.8, 1.2, len(reference.params))
    reference.params = params
    info = model_info(name)
    assert info.model_id == int(pycolmap.CameraModelId.__members__[name])
    assert info is model_info(info.model_id)
    assert info.num_params == len(reference.params)
    assert ",".join(info.param_names) == reference.params_info.replace(" ", "")
    if not reference.focal_length_idxs():
        with pytest.raises(DatasetError, match="no pinhole"):
            pinhole_part(name, params)
        return
    expected = (
        reference.focal_length_x,
        reference.focal_length_y,
        reference.principal_point_x,
        reference.principal_point_y,
    )
    assert pinhole_part(name, params) == pytest.approx(expected, rel=0, abs=0)
    camera = Camera(7, name, 640, 480, params)
    np.testing.assert_array_equal(camera.K(), reference.calibration_matrix())


@pytest.mark.parametrize("name", ["SIMPLE_PINHOLE", "PINHOLE"])
def test_pinhole_projection_matches_pycolmap(name: str) -> None:
    """K @ x / z equals pycolmap's img_from_cam for the distortion-free models."""
    reference = pycolmap.Camera.create_from_model_name(1, name, 700.0, 800, 600)
    reference.params = np.asarray(reference.params) + np.arange(len(reference.params)) * 3.0
    camera = Camera(1, name, 800, 600, np.asarray(reference.params))
    points = np.random.default_rng(0).uniform([-2, -2, 1], [2, 2, 6], size=(50, 3))
    projected = points @ camera.K().T
    ours = projected[:, :2] / projected[:, 2:]
    np.testing.assert_allclose(ours, reference.img_from_cam(points), atol=1e-9)
    assert camera.is_pinhole


def test_bad_models_and_parameter_counts() -> None:
    with pytest.raises(DatasetError, match="unknown COLMAP camera model 'PINHOL'"):
        pinhole_part("PINHOL", np.ones(4))
    with pytest.raises(DatasetError, match="takes 8 parameters"):
        pinhole_part("OPENCV", np.ones(4))
    with pytest.raises(DatasetError, match="unknown"):
        model_info(99)
