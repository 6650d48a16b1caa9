"""Property tests: any valid configuration gives finite terrain and sound cameras."""
from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from esgs.core.terrain import RIG_KINDS, RenderConfig, RigConfig, TerrainConfig, generate_terrain, make_camera_rig

terrain_configs = st.builds(
    TerrainConfig,
    resolution=st.sampled_from([33, 48, 65]),
    extent_m=st.floats(10.0, 200.0),
    relief_amplitude_m=st.floats(0.0, 3.0),
    relief_wavelength_m=st.floats(15.0, 60.0),
    relief_octaves=st.integers(1, 8),
    ridged_fraction=st.floats(0.0, 1.0),
    slope_deg=st.floats(-30.0, 30.0),
    slope_azimuth_deg=st.floats(-360.0, 360.0),
    scarp_height_m=st.floats(0.0, 10.0),
    layer_thickness_m=st.sampled_from([0.0, 0.3, 1.0]),
    crater_count=st.integers(0, 40),
    crater_min_diameter_m=st.floats(0.5, 3.0),
    crater_max_diameter_m=st.floats(5.0, 80.0),
    crater_sfd_exponent=st.floats(0.5, 4.0),
    rock_abundance=st.sampled_from([0.0, 0.02, 0.1]),
    rock_min_diameter_m=st.sampled_from([1.0, 1.5]),
    sand_fraction=st.floats(0.0, 1.0),
    dune_amplitude_m=st.floats(0.0, 3.0),
    dune_wavelength_m=st.floats(30.0, 60.0),
    wind_azimuth_deg=st.floats(0.0, 360.0),
)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(config=terrain_configs, seed=st.integers(0, 2 ** 32 - 1))
def test_any_valid_terrain_is_finite_and_consistent(config, seed):
    terrain = generate_terrain(config, seed=seed)
    assert np.isfinite(terrain.heights).all() and np.isfinite(terrain.sand_mask).all()
    assert terrain.sand_mask.min() >= 0.0 and terrain.sand_mask.max() <= 1.0
    assert terrain.craters.shape == (config.crater_count, 5)
    assert np.isfinite(terrain.rocks).all()
    if len(terrain.rocks):
        half = config.extent_m / 2
        assert np.abs(terrain.rocks[:, :2]).max() <= half + 1e-9


rig_configs = st.builds(
    RigConfig,
    kind=st.sampled_from(RIG_KINDS),
    views=st.integers(1, 12),
    height_m=st.floats(0.5, 40.0),
    radius_m=st.floats(0.5, 30.0),
    pitch_deg=st.floats(-85.0, -10.0),
    spacing_m=st.floats(0.1, 3.0),
    heading_deg=st.floats(-180.0, 360.0),
    sweep_deg=st.floats(10.0, 360.0),
    wander_m=st.floats(0.0, 3.0),
    look_offset_deg=st.floats(-180.0, 180.0),
    yaw_sweep_deg=st.floats(0.0, 30.0),
    pivot_offset_m=st.floats(0.0, 1.0),
    center_x_m=st.floats(-10.0, 10.0),
    center_y_m=st.floats(-10.0, 10.0),
    jitter_deg=st.floats(0.0, 5.0),
)

_TERRAIN = None


def shared_terrain():
    global _TERRAIN
    if _TERRAIN is None:
        _TERRAIN = generate_terrain(TerrainConfig(resolution=65, extent_m=80.0, relief_amplitude_m=2.0,
                                                  relief_wavelength_m=25.0, crater_count=10), seed=0)
    return _TERRAIN


@settings(max_examples=60, deadline=None)
@given(rig=rig_configs, seed=st.integers(0, 2 ** 32 - 1), aspect=st.sampled_from([(64, 64), (96, 54), (54, 96)]))
def test_any_valid_rig_gives_sound_cameras(rig, seed, aspect):
    terrain = shared_terrain()
    render = RenderConfig(width=aspect[0], height=aspect[1], fov_deg=50.0)
    poses = make_camera_rig(rig, render, terrain, seed=seed)
    assert len(poses) == rig.views
    for pose in poses:
        rotation = pose.rotation
        assert np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)
        assert math.isclose(np.linalg.det(rotation), 1.0, abs_tol=1e-9)
        x, y, z = pose.camera_center
        assert z >= terrain.height_at(x, y) + rig.min_clearance_m - 1e-9
        if rig.kind == "orbit":
            # Aimed at the site centre, up to the jitter.
            to_target = pose.target - pose.camera_center
            cosine = np.dot(to_target, pose.forward) / np.linalg.norm(to_target)
            assert math.degrees(math.acos(min(1.0, cosine))) <= 1.5 * rig.jitter_deg + 1e-3
        else:
            assert pose.forward[2] < 0  # looks down at least a little
        if np.isfinite(pose.target).all():
            pixels, depth = pose.project(pose.target[None])
            assert depth[0] > 0
            assert -1e-6 <= pixels[0, 0] <= pose.width + 1e-6 and -1e-6 <= pixels[0, 1] <= pose.height + 1e-6
    if rig.kind == "rover_traverse" and rig.views == 1 and rig.yaw_sweep_deg == 0 and rig.jitter_deg == 0:
        yaw = math.degrees(math.atan2(poses[0].forward[1], poses[0].forward[0]))
        expected = rig.heading_deg + rig.look_offset_deg
        assert abs((yaw - expected + 180.0) % 360.0 - 180.0) < 1e-6
