"""Mesh rigs on an analytic bowl (no Blender): the mixed aerial + rover rig with sky."""
from __future__ import annotations

import numpy as np
import pytest

from esgs.core.errors import ConfigError, DatasetError
from esgs.core.terrain.config import RenderConfig
from esgs.core.terrain.mesh_scene import MeshRigConfig, make_mesh_rig

CURVATURE = 0.002  # z = a (x^2 + y^2): 20 m high at the square's edge, like a crater
HALF = 100.0


def bowl_cast(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance along each ray to the bowl inside |x|, |y| <= HALF (inf on a miss)."""
    o, d = np.asarray(origins, float), np.asarray(directions, float)
    a = CURVATURE * (d[:, 0] ** 2 + d[:, 1] ** 2)
    b = 2 * CURVATURE * (o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]) - d[:, 2]
    c = CURVATURE * (o[:, 0] ** 2 + o[:, 1] ** 2) - o[:, 2]
    out = np.full(len(o), np.inf)
    for index in range(len(o)):
        if abs(a[index]) < 1e-15:
            roots = [-c[index] / b[index]] if abs(b[index]) > 1e-15 else []
        else:
            disc = b[index] ** 2 - 4 * a[index] * c[index]
            if disc < 0:
                continue
            root = np.sqrt(disc)
            roots = sorted([(-b[index] - root) / (2 * a[index]), (-b[index] + root) / (2 * a[index])])
        for t in roots:
            if t > 1e-9:
                hit = o[index] + t * d[index]
                if abs(hit[0]) <= HALF and abs(hit[1]) <= HALF:
                    out[index] = t
                break  # the first crossing decides: beyond the square's edge the ray leaves the mesh
    return out


BOUNDS_MIN = np.array([-HALF, -HALF, 0.0])
BOUNDS_MAX = np.array([HALF, HALF, CURVATURE * 2 * HALF**2])


def _render() -> RenderConfig:
    return RenderConfig(width=64, height=36, samples=1, fov_deg=60.0)


def _mixed(**overrides) -> MeshRigConfig:
    settings = dict(kind="mixed", views=10, orbit_radius_m=40.0, orbit_height_m=30.0, border_margin_m=5.0,
                    probe_grid=5, max_attempts=200)
    return MeshRigConfig(**{**settings, **overrides})


def test_mixed_rig_has_aerial_views_then_rover_views_with_sky():
    rig = _mixed()
    poses = make_mesh_rig(rig, _render(), bowl_cast, BOUNDS_MIN, BOUNDS_MAX, seed=3)
    assert [pose.name for pose in poses] == [f"view_{index:03d}" for index in range(10)]
    aerial, rover = poses[:6], poses[6:]  # 40 % rover views by default
    centres = np.stack([pose.camera_center for pose in poses])
    ground = CURVATURE * (centres[:, 0] ** 2 + centres[:, 1] ** 2)
    np.testing.assert_allclose(np.linalg.norm(centres[:6, :2] - aerial[0].target[:2], axis=1), 40.0, rtol=1e-9)
    np.testing.assert_allclose(centres[6:, 2] - ground[6:], rig.mast_height_m, atol=1e-6)
    # rover views start inside the orbit's circle and look near the horizon
    assert np.all(np.linalg.norm(centres[6:, :2] - aerial[0].target[:2], axis=1) <= 40.0 + rig.spacing_m * 4)
    forward = np.stack([pose.forward for pose in rover])
    np.testing.assert_allclose(np.degrees(np.arcsin(forward[:, 2])), rig.rover_pitch_deg, atol=1e-6)
    # the rover views see sky in their upper rows, the surface in their lower half
    rows = np.linspace(0.5, 35.5, 7)
    sky, lower_hits = 0, []
    for pose in rover:
        pixels = np.stack(np.meshgrid(np.linspace(0.5, 63.5, 7), rows), -1).reshape(-1, 2)
        distances = bowl_cast(np.repeat(pose.camera_center[None], len(pixels), 0), pose.pixel_rays(pixels))
        sky += int(np.isinf(distances).sum())
        lower_hits.append(np.isfinite(distances[pixels[:, 1] >= 18]).all())
    assert sky > 0 and all(lower_hits)
    # aerial views see only surface
    for pose in aerial:
        pixels = np.stack(np.meshgrid(np.linspace(0.5, 63.5, 7), rows), -1).reshape(-1, 2)
        assert np.isfinite(bowl_cast(np.repeat(pose.camera_center[None], len(pixels), 0), pose.pixel_rays(pixels))).all()
    again = make_mesh_rig(rig, _render(), bowl_cast, BOUNDS_MIN, BOUNDS_MAX, seed=3)
    np.testing.assert_array_equal(np.stack([p.world_to_camera for p in poses]),
                                  np.stack([p.world_to_camera for p in again]))


def test_mixed_rig_rover_views_count_and_errors():
    poses = make_mesh_rig(_mixed(rover_views=3), _render(), bowl_cast, BOUNDS_MIN, BOUNDS_MAX, seed=1)
    assert len(poses) == 10
    centres = np.stack([pose.camera_center for pose in poses])
    assert np.all(centres[7:, 2] - CURVATURE * (centres[7:, 0] ** 2 + centres[7:, 1] ** 2) < 2.0 + 1e-6)
    with pytest.raises(ConfigError, match="rover_views"):
        _mixed(rover_views=10).validate()
    with pytest.raises(ConfigError, match="views"):
        _mixed(views=3).validate()
    # looking steeply down no rover view sees the sky: a clear error with the setting to change
    with pytest.raises(DatasetError, match="could not place") as error:
        make_mesh_rig(_mixed(rover_pitch_deg=-60.0, max_attempts=20), _render(), bowl_cast, BOUNDS_MIN, BOUNDS_MAX)
    assert "rover_pitch_deg" in str(error.value.hint)


def test_mixed_rig_is_placed_on_flat_ground_with_the_default_pitch():
    def plane_cast(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """A flat 400 m square at z = 0 (inf where a ray misses it)."""
        o, d = np.asarray(origins, float), np.asarray(directions, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(d[:, 2] < 0, -o[:, 2] / d[:, 2], np.inf)
        hit = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        inside = (np.abs(hit[:, 0]) <= 200) & (np.abs(hit[:, 1]) <= 200)
        return np.where(np.isfinite(t) & inside & (t > 0), t, np.inf)

    rig = MeshRigConfig(kind="mixed", views=8, orbit_radius_m=30.0, orbit_height_m=20.0, border_margin_m=10.0,
                        probe_grid=9, max_attempts=100)
    poses = make_mesh_rig(rig, _render(), plane_cast, np.array([-200.0, -200.0, 0.0]), np.array([200.0, 200.0, 0.0]),
                          seed=0)
    rover = poses[-3:]  # 40 % of 8 views, rounded
    assert all(abs(pose.camera_center[2] - rig.mast_height_m) < 1e-9 for pose in rover)


def test_a_scene_jobs_site_center_moves_the_mixed_rig(tmp_path):
    import dataclasses

    from esgs.core.terrain.scene_job import SceneJob

    mesh = tmp_path / "terrain.glb"
    mesh.write_bytes(b"glTF")  # only its existence is checked here
    job = SceneJob(mesh=str(mesh), rig="mixed", views=10, site_center=" 30, -20")
    rig = job.scene_config().rig
    assert (rig.center_x_m, rig.center_y_m) == (30.0, -20.0)
    assert SceneJob(mesh=str(mesh), rig="mixed").scene_config().rig.center_x_m is None  # the footprint's middle
    rig = dataclasses.replace(rig, orbit_radius_m=25.0, orbit_height_m=20.0, border_margin_m=5.0, probe_grid=5,
                              max_attempts=200)
    poses = make_mesh_rig(rig, _render(), bowl_cast, BOUNDS_MIN, BOUNDS_MAX, seed=2)
    centres = np.stack([pose.camera_center for pose in poses])
    np.testing.assert_allclose(poses[0].target[:2], (30.0, -20.0))
    np.testing.assert_allclose(np.linalg.norm(centres[:6, :2] - (30.0, -20.0), axis=1), 25.0, rtol=1e-9)
    assert np.all(np.linalg.norm(centres[6:, :2] - (30.0, -20.0), axis=1) <= 25.0 + rig.spacing_m * 4)


@pytest.mark.parametrize("center, message", [("30", "two numbers X,Y"), ("a,b", "two numbers X,Y"),
                                             ("1,2,3", "two numbers X,Y"), ("inf,0", "finite")])
def test_a_bad_site_center_is_refused_with_an_example(center, message):
    from esgs.core.terrain.scene_job import SceneJob

    with pytest.raises(ConfigError, match=message):
        SceneJob(mesh="terrain.glb", rig="mixed", site_center=center).validate()


def test_a_site_center_needs_a_mesh_orbit_or_mixed_rig():
    from esgs.core.terrain.scene_job import SceneJob

    for job in (SceneJob(site_center="1,2"), SceneJob(mesh="terrain.glb", rig="traverse", site_center="1,2")):
        with pytest.raises(ConfigError, match="--site-center applies to --mesh scenes with --rig orbit or mixed"):
            job.validate()
