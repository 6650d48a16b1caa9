"""Camera rigs: proper poses in OpenCV axes, above the ground, aimed at it, overlapping."""
from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from esgs.core.errors import ConfigError
from esgs.core.terrain import (
    RIG_KINDS, RenderConfig, RigConfig, TerrainConfig, generate_terrain, list_presets, load_preset,
    make_camera_rig, views_beyond_terrain,
)
from esgs.core.terrain.rigs import look_rotation

RENDER = RenderConfig(width=320, height=180, fov_deg=60.0)


@functools.lru_cache(maxsize=None)
def preset_scene(name: str):
    """Preset config (seed 3), its terrain and cameras, as a user would get them."""
    config = load_preset(name, seed=3)
    terrain = generate_terrain(config.terrain, seed=config.seed)
    return config, terrain, make_camera_rig(config.rig, config.render, terrain, seed=config.seed)


@functools.lru_cache(maxsize=None)
def hilly_terrain():
    config = TerrainConfig(resolution=129, extent_m=100.0, relief_amplitude_m=2.0, relief_wavelength_m=30.0,
                           crater_count=20, sand_fraction=0.0)
    return generate_terrain(config, seed=1)


def rig(kind: str, **changes) -> RigConfig:
    values = dict(kind=kind, views=12, radius_m=15.0, height_m=2.0 if kind in ("rover_traverse", "station_panorama") else 20.0,
                  pitch_deg=-40.0, jitter_deg=1.0)
    values.update(changes)
    return RigConfig(**values)


@pytest.mark.parametrize("kind", RIG_KINDS)
def test_poses_are_proper_rotations_with_expected_intrinsics(kind):
    poses = make_camera_rig(rig(kind), RENDER, hilly_terrain(), seed=0)
    assert [pose.name for pose in poses] == [f"view_{index:03d}" for index in range(12)]
    for pose in poses:
        rotation = pose.world_to_camera[:3, :3]
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        np.testing.assert_array_equal(pose.world_to_camera[3], [0, 0, 0, 1])
        focal = 160.0 / math.tan(math.radians(30.0))
        np.testing.assert_allclose(pose.K, [[focal, 0, 160.0], [0, focal, 90.0], [0, 0, 1]])
        assert (pose.width, pose.height) == (320, 180)
        # No roll: the camera x axis is horizontal, and image "down" points downward.
        assert abs(rotation[0, 2]) < 1e-12
        assert rotation[1, 2] <= 1e-12


@pytest.mark.parametrize("kind", RIG_KINDS)
def test_deterministic_by_seed(kind):
    terrain = hilly_terrain()
    first = make_camera_rig(rig(kind), RENDER, terrain, seed=4)
    again = make_camera_rig(rig(kind), RENDER, terrain, seed=4)
    other = make_camera_rig(rig(kind), RENDER, terrain, seed=5)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.world_to_camera, b.world_to_camera)
    assert any(not np.allclose(a.world_to_camera, b.world_to_camera) for a, b in zip(first, other))


@pytest.mark.parametrize("kind", RIG_KINDS)
def test_cameras_stay_above_the_ground(kind):
    terrain = hilly_terrain()
    config = rig(kind)
    for pose in make_camera_rig(config, RENDER, terrain, seed=0):
        x, y, z = pose.camera_center
        assert z >= terrain.height_at(x, y) + config.min_clearance_m - 1e-9


def test_rover_mast_height_above_terrain_and_spacing():
    terrain = hilly_terrain()
    config = rig("rover_traverse", views=20, spacing_m=0.5, wander_m=0.5, jitter_deg=0.0, heading_deg=30.0)
    poses = make_camera_rig(config, RENDER, terrain, seed=0)
    centres = np.stack([pose.camera_center for pose in poses])
    np.testing.assert_allclose(centres[:, 2], terrain.height_at(centres[:, 0], centres[:, 1]) + 2.0, atol=1e-9)
    steps = np.linalg.norm(np.diff(centres[:, :2], axis=0), axis=1)
    assert np.all((steps > 0.45) & (steps < 0.6))
    # Driving toward heading 30 deg, looking roughly that way and down by the pitch.
    travel = centres[-1, :2] - centres[0, :2]
    assert math.degrees(math.atan2(travel[1], travel[0])) == pytest.approx(30.0, abs=5.0)
    for pose in poses:
        forward = pose.forward
        assert math.degrees(math.asin(forward[2])) == pytest.approx(-40.0, abs=1e-9)
        assert np.dot(forward[:2], travel) > 0


def test_panorama_rotates_in_place_unless_offset():
    terrain = hilly_terrain()
    poses = make_camera_rig(rig("station_panorama", jitter_deg=0.0), RENDER, terrain, seed=0)
    centres = np.stack([pose.camera_center for pose in poses])
    np.testing.assert_allclose(centres, np.broadcast_to(centres[0], centres.shape), atol=1e-9)
    yaws = np.degrees(np.unwrap([math.atan2(p.forward[1], p.forward[0]) for p in poses]))
    np.testing.assert_allclose(np.diff(yaws), 30.0, atol=1e-9)
    offset = make_camera_rig(rig("station_panorama", jitter_deg=0.0, pivot_offset_m=0.3), RENDER, terrain, seed=0)
    radii = [np.linalg.norm(pose.camera_center[:2]) for pose in offset]
    np.testing.assert_allclose(radii, 0.3, atol=1e-9)


def test_orbit_circles_and_aims_at_the_centre():
    terrain = hilly_terrain()
    poses = make_camera_rig(rig("orbit", jitter_deg=0.0, center_x_m=3.0, center_y_m=-2.0), RENDER, terrain, seed=0)
    ground = float(terrain.height_at(3.0, -2.0))
    for pose in poses:
        np.testing.assert_allclose(pose.target, [3.0, -2.0, ground])
        assert np.linalg.norm(pose.camera_center[:2] - [3.0, -2.0]) == pytest.approx(15.0)
        pixels, depth = pose.project(pose.target[None])
        np.testing.assert_allclose(pixels[0], [160.0, 90.0], atol=1e-6)
        assert depth[0] > 0


def test_nadir_looks_straight_down_on_a_grid():
    poses = make_camera_rig(rig("aerial_nadir", views=9, jitter_deg=0.0), RENDER, hilly_terrain(), seed=0)
    for pose in poses:
        np.testing.assert_allclose(pose.forward, [0, 0, -1], atol=1e-12)
    xy = np.round(np.stack([pose.camera_center[:2] for pose in poses]), 6)
    assert sorted(set(xy[:, 0])) == [-15.0, 0.0, 15.0] and sorted(set(xy[:, 1])) == [-15.0, 0.0, 15.0]


def test_look_rotation_axes():
    # Looking along +x, level: right is -y, down is -z (OpenCV x right, y down, z forward).
    np.testing.assert_allclose(look_rotation(0.0, 0.0), [[0, -1, 0], [0, 0, -1], [1, 0, 0]], atol=1e-12)


def test_blender_matrix_looks_along_minus_z_with_y_up():
    pose = make_camera_rig(rig("orbit"), RENDER, hilly_terrain(), seed=0)[0]
    blender = pose.blender_matrix_world()
    np.testing.assert_allclose(blender[:3, 3], pose.camera_center)
    np.testing.assert_allclose(-blender[:3, 2], pose.forward, atol=1e-12)
    np.testing.assert_allclose(blender[:3, 1], -pose.rotation[1], atol=1e-12)


def test_pixel_rays_invert_projection():
    pose = make_camera_rig(rig("aerial_oblique"), RENDER, hilly_terrain(), seed=0)[3]
    pixels = np.array([[0.5, 0.5], [319.5, 179.5], [100.0, 40.0]])
    points = pose.camera_center + 7.0 * pose.pixel_rays(pixels)
    projected, depth = pose.project(points)
    np.testing.assert_allclose(projected, pixels, atol=1e-9)
    assert np.all(depth > 0)


NO_SKY = [name for name in list_presets() if not load_preset(name).sky]
WITH_SKY = [name for name in list_presets() if load_preset(name).sky]


@pytest.mark.parametrize("name", NO_SKY)
def test_no_sky_presets_see_only_terrain_and_aim_at_it(name):
    config, terrain, poses = preset_scene(name)
    assert len(poses) == config.rig.views
    assert views_beyond_terrain(poses, terrain) == []
    for pose in poses:
        assert np.isfinite(pose.target).all()
        pixels, depth = pose.project(pose.target[None])
        assert depth[0] > 0
        assert 0 <= pixels[0, 0] <= pose.width and 0 <= pixels[0, 1] <= pose.height
    centres = np.stack([pose.camera_center for pose in poses])
    if config.rig.kind == "rover_traverse":
        np.testing.assert_allclose(centres[:, 2] - terrain.height_at(centres[:, 0], centres[:, 1]),
                                   config.rig.height_m, atol=1e-6)
    if config.rig.kind == "station_panorama":
        # The mast stands on the ground at the station; the camera pans around its top.
        ground = terrain.height_at(config.rig.center_x_m, config.rig.center_y_m)
        np.testing.assert_allclose(centres[:, 2] - ground, config.rig.height_m, atol=1e-6)


@pytest.mark.parametrize("name", WITH_SKY)
def test_sky_presets_show_the_horizon(name):
    _, terrain, poses = preset_scene(name)
    assert set(views_beyond_terrain(poses, terrain)) == {pose.name for pose in poses}
    for pose in poses:
        # The top-centre ray rises above the horizontal; the bottom-centre ray hits ground.
        top, bottom = pose.pixel_rays(np.array([[pose.width / 2, 0.0], [pose.width / 2, float(pose.height)]]))
        assert top[2] > 0
        assert np.isfinite(terrain.raycast(pose.camera_center[None], bottom[None])[0])


def ground_overlap(first, second, terrain, samples: int = 12) -> float:
    """Share of the ground seen by ``first`` (a pixel grid) that falls inside ``second``'s image."""
    u, v = np.meshgrid(np.linspace(0.5, first.width - 0.5, samples), np.linspace(0.5, first.height - 0.5, samples))
    rays = first.pixel_rays(np.stack([u.ravel(), v.ravel()], axis=1))
    distances = terrain.raycast(np.repeat(first.camera_center[None], len(rays), axis=0), rays)
    hit = np.isfinite(distances)
    points = first.camera_center + distances[hit, None] * rays[hit]
    pixels, depth = second.project(points)
    inside = (depth > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] <= second.width) & (pixels[:, 1] >= 0) & (pixels[:, 1] <= second.height)
    return float(inside.mean()) if hit.any() else 0.0


@pytest.mark.parametrize("name", NO_SKY)
def test_consecutive_views_overlap(name):
    config, terrain, poses = preset_scene(name)
    overlaps = [ground_overlap(a, b, terrain) for a, b in zip(poses[:-1], poses[1:])]
    # Photogrammetry rules of thumb ask for >= 50-60% forward overlap.
    assert np.median(overlaps) > 0.5
    assert min(overlaps) > 0.3


def test_bad_rig_raises_before_work():
    with pytest.raises(ConfigError, match="rig.views"):
        make_camera_rig(RigConfig(views=0), RENDER, hilly_terrain())
    with pytest.raises(ConfigError, match="render.width"):
        make_camera_rig(RigConfig(), RenderConfig(width=-1), hilly_terrain())


@pytest.mark.parametrize("kind", RIG_KINDS)
def test_stereo_pairs_share_orientation_and_baseline(kind):
    terrain = hilly_terrain()
    config = rig(kind, views=10, stereo_baseline_m=0.424, jitter_deg=0.0)
    poses = make_camera_rig(config, RENDER, terrain, seed=2)
    assert len(poses) == 10
    for left, right in zip(poses[0::2], poses[1::2]):
        np.testing.assert_allclose(left.rotation, right.rotation, atol=1e-12)
        offset = right.camera_center - left.camera_center
        if abs(offset[2]) < 1e-9:  # neither camera lifted by the ground clearance
            np.testing.assert_allclose(offset, 0.424 * left.rotation[0], atol=1e-9)
        # The right camera sits to the right: positive x in the left camera's frame.
        assert (left.rotation @ offset)[0] == pytest.approx(0.424, abs=1e-9)
    with pytest.raises(ConfigError, match="rig.views.*even"):
        make_camera_rig(rig(kind, views=9, stereo_baseline_m=0.424), RENDER, terrain)


def test_ground_depth_matches_a_flat_plane():
    from esgs.core.terrain import Terrain, ground_depth
    heights = np.full((65, 65), 1.0, dtype=np.float32)
    terrain = Terrain(heights=heights, extent_m=200.0, sand_mask=np.zeros_like(heights))
    pose = make_camera_rig(RigConfig(kind="station_panorama", views=1, height_m=2.0, pitch_deg=-30.0),
                           RENDER, terrain, seed=0)[0]
    pixels = np.array([[160.0, 90.0], [10.0, 170.0], [300.0, 120.0], [160.0, 0.0]])
    depth = ground_depth(pose, terrain, pixels)
    rays = pose.pixel_rays(pixels)
    # Camera 2 m above the plane z = 1: distance along each ray = 2 / -dz.
    expected = (2.0 / -rays[:, 2]) * (rays @ pose.forward)
    np.testing.assert_allclose(depth, expected, rtol=1e-6)
    # The image centre looks 30 deg down: z-depth there = 2 / sin(30 deg).
    assert depth[0] == pytest.approx(4.0, rel=1e-6)


def test_panorama_overlap_narrows_a_sweep_too_wide_for_its_views():
    terrain = hilly_terrain()

    def pan_angles(**changes):
        poses = make_camera_rig(rig("station_panorama", jitter_deg=0.0, heading_deg=20.0, **changes), RENDER, terrain)
        return np.degrees(np.unwrap([math.atan2(p.forward[1], p.forward[0]) for p in poses]))

    # 6 views over 360 deg step 60 deg: a 60 deg camera would leave no overlap at all.
    np.testing.assert_allclose(np.diff(pan_angles(views=6)), 60.0, atol=1e-9)
    # At least 40 % overlap: steps of 36 deg, the narrower sweep centred on the heading.
    narrowed = pan_angles(views=6, pan_overlap=0.4)
    np.testing.assert_allclose(np.diff(narrowed), 36.0, atol=1e-9)
    assert narrowed.mean() == pytest.approx(20.0, abs=1e-9)
    # Enough views already overlap: the full circle from the heading is kept.
    full = pan_angles(views=30, pan_overlap=0.4)
    np.testing.assert_allclose(np.diff(full), 12.0, atol=1e-9)
    assert full[0] == pytest.approx(20.0, abs=1e-9)
    # A partial sweep is narrowed the same way (6 views over 270 deg: step 54 -> 36 deg).
    np.testing.assert_allclose(np.diff(pan_angles(views=6, sweep_deg=270.0, pan_overlap=0.4)), 36.0, atol=1e-9)
    with pytest.raises(ConfigError, match="rig.pan_overlap"):
        make_camera_rig(rig("station_panorama", pan_overlap=1.0), RENDER, terrain)


def test_navcam_panorama_with_few_views_still_chains_its_pointings():
    # With 12 views (6 stereo pointings) a 360 deg pan would leave 15 deg gaps between the
    # 45 deg frames; the preset's pan_overlap keeps neighbouring pointings tied together.
    config = load_preset("navcam_panorama", seed=3, views=12, resolution=(320, 180))
    config.validate()
    terrain = generate_terrain(config.terrain, seed=config.seed)
    poses = make_camera_rig(config.rig, config.render, terrain, seed=config.seed)
    left = poses[0::2]
    overlaps = [ground_overlap(a, b, terrain, samples=20) for a, b in zip(left[:-1], left[1:])]
    assert min(overlaps) > 0.2
    # and every pair has parallax: the two centres are a stereo baseline apart
    for a, b in zip(poses[0::2], poses[1::2]):
        assert np.linalg.norm(a.camera_center - b.camera_center) == pytest.approx(config.rig.stereo_baseline_m, abs=1e-9)


@pytest.mark.parametrize("views", [2, 3, 5, 30])
def test_short_rover_paths_keep_their_heading(views):
    # A path of a few views used to wander by the full wander_m over a few decimetres: a
    # zigzag that turned the cameras up to ~70 deg off heading_deg (and, for
    # layered_outcrop with 2 views, past the terrain's edge).
    terrain = hilly_terrain()
    for seed in range(6):
        config = rig("rover_traverse", views=views, spacing_m=0.6, wander_m=1.0, jitter_deg=0.0, heading_deg=30.0)
        poses = make_camera_rig(config, RENDER, terrain, seed=seed)
        yaws = np.array([math.degrees(math.atan2(p.forward[1], p.forward[0])) for p in poses])
        assert np.all(np.abs(yaws - 30.0) <= 20.0 + 1e-9)
    # a long path keeps its full wander: the lateral offsets reach ~wander_m
    long_poses = make_camera_rig(rig("rover_traverse", views=60, spacing_m=0.5, wander_m=1.0, jitter_deg=0.0),
                                 RENDER, terrain, seed=1)
    lateral = np.array([p.camera_center[1] for p in long_poses])
    assert np.abs(lateral).max() > 0.9


@pytest.mark.parametrize("seed", range(6))
def test_layered_outcrop_validates_with_two_views(seed):
    load_preset("layered_outcrop", seed=seed, views=2).validate()
