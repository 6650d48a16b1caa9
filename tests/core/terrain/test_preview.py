"""Preview images: shading follows the sun, north is up, cameras land where they are."""
from __future__ import annotations

import math

import numpy as np
import pytest

from esgs.core.terrain import RenderConfig, RigConfig, Terrain, make_camera_rig
from esgs.core.terrain.preview import hillshade, overview_image


def plane(slope_x: float) -> Terrain:
    axis = np.linspace(-10.0, 10.0, 41)
    heights = (slope_x * axis[None, :] + np.zeros((41, 1))).astype(np.float32)
    return Terrain(heights=heights, extent_m=20.0, sand_mask=np.zeros_like(heights))


def test_hillshade_is_lambertian():
    assert hillshade(plane(0.0), (0.0, 0.0, 1.0)) == pytest.approx(1.0)
    # A slope rising toward +x faces -x: lit from -x it is brighter than lit from +x.
    elevation = math.radians(30.0)
    from_west = (-math.cos(elevation), 0.0, math.sin(elevation))
    from_east = (math.cos(elevation), 0.0, math.sin(elevation))
    tilted = plane(0.5)
    normal = np.array([-0.5, 0.0, 1.0]) / math.sqrt(1.25)
    assert hillshade(tilted, from_west)[20, 20] == pytest.approx(float(normal @ np.array(from_west)))
    assert hillshade(tilted, from_east)[20, 20] < hillshade(tilted, from_west)[20, 20]


def test_overview_marks_cameras_north_up():
    terrain = plane(0.0)
    rig = RigConfig(kind="station_panorama", views=1, height_m=2.0, center_x_m=5.0, center_y_m=5.0, pitch_deg=-60.0)
    poses = make_camera_rig(rig, RenderConfig(width=64, height=48), terrain)
    image = overview_image(terrain, (0.0, 0.0, 1.0), poses, marker_px=0)
    assert image.shape == (41, 41, 3) and image.dtype == np.uint8
    # (x, y) = (5, 5) is column 30, row 30 from the south, i.e. row 10 from the top.
    assert tuple(image[10, 30]) == (255, 25, 25)
    assert image[30, 30, 0] < 255  # nothing drawn at the mirrored (southern) spot
