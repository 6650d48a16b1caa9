"""Camera rigs over a terrain: rover traverse, station panorama, orbit, aerial oblique/nadir.

Every pose is built from a position, a yaw (azimuth of the viewing direction, ccw from +x)
and a pitch (elevation, negative looking down), with no roll: the camera's x axis stays
horizontal. Poses use OpenCV camera axes (x right, y down, z forward) and a pinhole K
whose pixel centres sit at +0.5 (pixel (0, 0) covers [0, 1] x [0, 1]), so the principal
point of a centred camera is (width / 2, height / 2). This matches COLMAP and gsplat.

Kinds (``RigConfig.kind``):

* ``rover_traverse``: a mast camera ``height_m`` above the ground, driving ``spacing_m``
  between views along a gently curving path centred on the site, looking forward with
  ``pitch_deg``; ``yaw_sweep_deg`` alternates views left / centre / right.
* ``station_panorama``: one mast position, the camera pans through ``sweep_deg``
  (``pan_overlap`` > 0 keeps neighbouring frames overlapping, narrowing the sweep when there
  are too few views). With ``pivot_offset_m = 0`` and no stereo baseline it is a pure
  rotation: no parallax, so SfM cannot triangulate it (real mast heads sit off the pan axis,
  ``pivot_offset_m`` ~0.2-0.5, and Navcams are stereo pairs, ``stereo_baseline_m`` 0.424).
* ``orbit``: a circle (or arc of ``sweep_deg``) of radius ``radius_m``, ``height_m`` above
  the site centre, every view aimed at the site centre.
* ``aerial_oblique``: aim points on a serpentine grid over a square of half-size
  ``radius_m``; each camera sits back along its flight line so its central ray, tilted by
  ``pitch_deg``, meets its aim point from ``height_m`` above it.
* ``aerial_nadir``: the same grid, cameras ``height_m`` above the site centre's ground,
  looking straight down.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from .config import RenderConfig, RigConfig, TerrainConfig
from .heightfield import Terrain

_STREAM_RIG = 100

#: Largest angle between a rover path's local heading and ``heading_deg`` (its wander).
MAX_WANDER_TURN_DEG = 20.0

# Blender cameras look along their local -Z with +Y up; OpenCV looks along +Z with +Y down.
_OPENCV_TO_BLENDER = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class CameraPose:
    """One view. K: [3, 3] pinhole intrinsics (pixel centres at +0.5).

    world_to_camera: [4, 4] rigid transform to OpenCV camera axes (x right, y down,
    z forward). target: [3] the world point the view is aimed at (the ground hit of the
    central ray; the site centre for orbits), NaN when the central ray meets no ground.
    """

    name: str
    K: np.ndarray
    world_to_camera: np.ndarray
    width: int
    height: int
    target: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))

    @property
    def rotation(self) -> np.ndarray:
        """[3, 3] world-to-camera rotation."""
        return self.world_to_camera[:3, :3]

    @property
    def camera_center(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        return -self.rotation.T @ self.world_to_camera[:3, 3]

    @property
    def forward(self) -> np.ndarray:
        """[3] unit viewing direction in world coordinates."""
        return self.rotation[2].copy()

    @property
    def camera_to_world(self) -> np.ndarray:
        """[4, 4] inverse of ``world_to_camera``."""
        result = np.eye(4)
        result[:3, :3] = self.rotation.T
        result[:3, 3] = self.camera_center
        return result

    def blender_matrix_world(self) -> np.ndarray:
        """[4, 4] ``matrix_world`` for a Blender camera object (looks along -Z, +Y up)."""
        return self.camera_to_world @ _OPENCV_TO_BLENDER

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates [N, 2] (continuous, +0.5 centres) and depth along z [N] of world points [N, 3]."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        camera = points @ self.rotation.T + self.world_to_camera[:3, 3]
        depth = camera[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels = (camera @ self.K.T)[:, :2] / depth[:, None]
        return pixels, depth

    def pixel_rays(self, pixels: np.ndarray) -> np.ndarray:
        """Unit world directions [N, 3] through pixel coordinates [N, 2]."""
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        homogeneous = np.concatenate([pixels, np.ones((pixels.shape[0], 1))], axis=1)
        camera = homogeneous @ np.linalg.inv(self.K).T
        world = camera @ self.rotation
        return world / np.linalg.norm(world, axis=1, keepdims=True)

    def border_pixels(self, per_edge: int = 3) -> np.ndarray:
        """Pixel coordinates [4 * per_edge - 4, 2] around the image border (corners included)."""
        u = np.linspace(0.0, self.width, per_edge)
        v = np.linspace(0.0, self.height, per_edge)
        points = [(x, 0.0) for x in u] + [(x, float(self.height)) for x in u]
        points += [(0.0, y) for y in v[1:-1]] + [(float(self.width), y) for y in v[1:-1]]
        return np.asarray(points)


def intrinsics(render: RenderConfig) -> np.ndarray:
    """Pinhole K [3, 3] of ``render``: square pixels, principal point at the image centre."""
    focal = render.focal_px
    return np.array([[focal, 0.0, render.width / 2], [0.0, focal, render.height / 2], [0.0, 0.0, 1.0]])


def look_rotation(yaw_rad: float, pitch_rad: float) -> np.ndarray:
    """World-to-camera rotation [3, 3] (rows: right, down, forward) for a roll-free view."""
    forward = np.array([math.cos(pitch_rad) * math.cos(yaw_rad), math.cos(pitch_rad) * math.sin(yaw_rad),
                        math.sin(pitch_rad)])
    # Horizontal right vector from the yaw alone stays defined when looking straight down.
    right = np.array([math.sin(yaw_rad), -math.cos(yaw_rad), 0.0])
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


def pose_matrix(position: np.ndarray, yaw_rad: float, pitch_rad: float) -> np.ndarray:
    """world_to_camera [4, 4] of a camera at ``position`` [3] looking along (yaw, pitch)."""
    rotation = look_rotation(yaw_rad, pitch_rad)
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = -rotation @ np.asarray(position, dtype=np.float64)
    return matrix


def _grid_offsets(views: int, radius: float) -> list[tuple[float, float, int]]:
    """Serpentine grid over [-radius, radius]^2: (along, across, line index) per view."""
    lines = max(1, int(round(math.sqrt(views))))
    per_line = math.ceil(views / lines)
    across = np.linspace(-radius, radius, lines) if lines > 1 else np.zeros(1)
    along = np.linspace(-radius, radius, per_line) if per_line > 1 else np.zeros(1)
    result = []
    for line, offset in enumerate(across):
        order = along if line % 2 == 0 else along[::-1]
        result.extend((float(a), float(offset), line) for a in order)
    return result[:views]


def panorama_yaw_offsets_deg(sweep_deg: float, pointings: int, fov_deg: float, pan_overlap: float) -> np.ndarray:
    """Pan angles [pointings] of a station panorama, degrees from ``heading_deg``.

    A full circle starts at the heading and steps 360 / pointings; a partial sweep is centred
    on the heading. With ``pan_overlap`` > 0 the step is at most ``fov_deg * (1 - pan_overlap)``:
    neighbouring frames then always share that much of the horizontal field of view (as rover
    panoramas are planned, so frames can be tied together), and too few pointings cover less
    than ``sweep_deg``, centred on the heading.
    """
    index = np.arange(pointings, dtype=np.float64)
    full_circle = sweep_deg >= 360.0
    step = 360.0 / pointings if full_circle else (sweep_deg / (pointings - 1) if pointings > 1 else 0.0)
    if pan_overlap > 0 and step > fov_deg * (1.0 - pan_overlap):
        step = fov_deg * (1.0 - pan_overlap)
        full_circle = False
    if full_circle:
        return step * index
    return step * (index - (pointings - 1) / 2.0)


def _positions_and_angles(rig: RigConfig, terrain: Terrain, rng: np.random.Generator, fov_deg: float = 60.0):
    """Camera positions [V, 3], yaws [V], pitches [V] (radians) and orbit target or None.

    ``fov_deg``: the horizontal field of view (for the panorama's overlap).
    """
    views = rig.views
    center = np.array([rig.center_x_m, rig.center_y_m])
    heading = math.radians(rig.heading_deg)
    pitch = math.radians(rig.pitch_deg)
    jitter = math.radians(rig.jitter_deg)
    yaw_noise = rng.uniform(-jitter, jitter, views) if jitter > 0 else np.zeros(views)
    pitch_noise = rng.uniform(-jitter, jitter, views) if jitter > 0 else np.zeros(views)
    positions = np.zeros((views, 3))
    yaws = np.zeros(views)
    pitches = np.full(views, pitch)
    target = None

    if rig.kind == "rover_traverse":
        length = rig.spacing_m * (views - 1)
        direction = np.array([math.cos(heading), math.sin(heading)])
        lateral = np.array([-direction[1], direction[0]])
        phase = rng.uniform(0.0, 2.0 * math.pi)
        span = max(length, 1e-9)
        s = -length / 2 + rig.spacing_m * np.arange(views)
        # The path wanders by half a sine period over its length. On a short path (few views)
        # the full wander_m would make a zigzag whose heading, and so every camera's yaw,
        # swings far off heading_deg; keep the path's heading within MAX_WANDER_TURN_DEG.
        wander = min(rig.wander_m, math.tan(math.radians(MAX_WANDER_TURN_DEG)) * span / math.pi)
        offset = wander * np.sin(math.pi * s / span + phase)
        # Heading of the path (a single view has no path: it looks along heading_deg).
        slope = wander * math.pi / span * np.cos(math.pi * s / span + phase) if length > 0 else np.zeros(views)
        xy = center + s[:, None] * direction + offset[:, None] * lateral
        tangent = direction[None, :] + slope[:, None] * lateral[None, :]
        yaws = np.arctan2(tangent[:, 1], tangent[:, 0])
        yaws += math.radians(rig.look_offset_deg) + math.radians(rig.yaw_sweep_deg) * ((np.arange(views) % 3) - 1)
        positions[:, :2] = xy
        positions[:, 2] = terrain.height_at(xy[:, 0], xy[:, 1]) + rig.height_m
    elif rig.kind == "station_panorama":
        yaws = heading + np.radians(panorama_yaw_offsets_deg(rig.sweep_deg, views, fov_deg, rig.pan_overlap))
        ground = float(terrain.height_at(center[0], center[1]))
        positions[:, 0] = center[0] + rig.pivot_offset_m * np.cos(yaws)
        positions[:, 1] = center[1] + rig.pivot_offset_m * np.sin(yaws)
        positions[:, 2] = ground + rig.height_m
    elif rig.kind == "orbit":
        sweep = math.radians(rig.sweep_deg)
        if rig.sweep_deg >= 360.0:
            angles = heading + sweep * np.arange(views) / views
        else:
            angles = heading - sweep / 2 + (sweep * np.arange(views) / (views - 1) if views > 1 else np.zeros(views))
        ground = float(terrain.height_at(center[0], center[1]))
        target = np.array([center[0], center[1], ground])
        positions[:, 0] = center[0] + rig.radius_m * np.cos(angles)
        positions[:, 1] = center[1] + rig.radius_m * np.sin(angles)
        positions[:, 2] = ground + rig.height_m
    elif rig.kind in ("aerial_oblique", "aerial_nadir"):
        grid = _grid_offsets(views, rig.radius_m)
        along_axis = np.array([math.cos(heading), math.sin(heading)])
        across_axis = np.array([-along_axis[1], along_axis[0]])
        ground_center = float(terrain.height_at(center[0], center[1]))
        for index, (along, across, line) in enumerate(grid):
            aim = center + along * along_axis + across * across_axis
            yaw = heading if line % 2 == 0 else heading + math.pi
            yaws[index] = yaw
            if rig.kind == "aerial_nadir":
                positions[index] = (aim[0], aim[1], ground_center + rig.height_m)
            else:
                back = rig.height_m / math.tan(-pitch)
                xy = aim - back * np.array([math.cos(yaw), math.sin(yaw)])
                positions[index] = (xy[0], xy[1], float(terrain.height_at(aim[0], aim[1])) + rig.height_m)
        if rig.kind == "aerial_nadir":
            pitches[:] = -0.5 * math.pi
            pitch_noise[:] = 0.0
    else:  # validate() already rejects this; kept so a bypassed validation fails loudly
        raise ConfigError(f"rig.kind {rig.kind!r} is not known")

    # Keep every camera clear of the ground right below it (hills under an aerial grid or
    # an orbit); done before aiming so orbit views still point at their target.
    floor = terrain.height_at(positions[:, 0], positions[:, 1]) + rig.min_clearance_m
    positions[:, 2] = np.maximum(positions[:, 2], floor)
    yaws = yaws + yaw_noise
    pitches = np.clip(pitches + pitch_noise, -0.5 * math.pi, 0.5 * math.pi)
    if target is not None:
        # Aim every orbit view at the site centre (the jitter then only perturbs the aim).
        delta = target[None, :] - positions
        yaws = np.arctan2(delta[:, 1], delta[:, 0]) + yaw_noise
        pitches = np.clip(np.arctan2(delta[:, 2], np.hypot(delta[:, 0], delta[:, 1])) + pitch_noise,
                          -0.5 * math.pi, 0.5 * math.pi)
    return positions, yaws, pitches, target


def make_camera_rig(rig: RigConfig, render: RenderConfig, terrain: Terrain, seed: int = 0) -> list[CameraPose]:
    """Camera poses [rig.views] of kind ``rig.kind`` over ``terrain`` (deterministic for ``seed``).

    Names are ``view_000``, ``view_001``... (image stems); with a stereo baseline the even
    views are the left and the odd views the right cameras. Raises ConfigError on bad config.
    """
    rig.validate()
    render.validate()
    rng = np.random.default_rng([int(seed), _STREAM_RIG])
    if rig.stereo_baseline_m > 0:
        # Stereo: views / 2 pointings, each seen by a left and a right camera (parallel
        # axes, centres ``stereo_baseline_m`` apart along the horizontal right axis).
        positions, yaws, pitches, target = _positions_and_angles(dataclasses.replace(rig, views=rig.views // 2), terrain, rng,
                                                              render.fov_deg)
        right = np.stack([np.sin(yaws), -np.cos(yaws), np.zeros_like(yaws)], axis=1)
        half = 0.5 * rig.stereo_baseline_m
        positions = np.stack([positions - half * right, positions + half * right], axis=1).reshape(-1, 3)
        floor = terrain.height_at(positions[:, 0], positions[:, 1]) + rig.min_clearance_m
        positions[:, 2] = np.maximum(positions[:, 2], floor)
        yaws, pitches = np.repeat(yaws, 2), np.repeat(pitches, 2)
    else:
        positions, yaws, pitches, target = _positions_and_angles(rig, terrain, rng, render.fov_deg)
    K = intrinsics(render)
    poses = []
    for index in range(rig.views):
        poses.append(CameraPose(name=f"view_{index:03d}", K=K.copy(),
                                world_to_camera=pose_matrix(positions[index], float(yaws[index]), float(pitches[index])),
                                width=render.width, height=render.height))
    if target is not None:
        for pose in poses:
            pose.target = target.copy()
    else:
        origins = np.stack([pose.camera_center for pose in poses])
        directions = np.stack([pose.forward for pose in poses])
        distances = terrain.raycast(origins, directions)
        for pose, origin, direction, distance in zip(poses, origins, directions, distances):
            if np.isfinite(distance):
                pose.target = origin + distance * direction
    return poses


def ground_depth(pose: CameraPose, terrain: Terrain, pixels: np.ndarray) -> np.ndarray:
    """Depth along the camera z axis [N] of the bare ground seen through pixels [N, 2]; inf where none.

    An independent reference for rendered depth maps (Cycles' Depth pass is also z-depth).
    Rocks are not in the heightfield, so pixels showing a rock differ.
    """
    rays = pose.pixel_rays(pixels)
    origins = np.repeat(pose.camera_center[None, :], rays.shape[0], axis=0)
    distances = terrain.raycast(origins, rays)
    return distances * (rays @ pose.forward)


def _large_scale_terrain(config: TerrainConfig) -> Terrain:
    """A coarse terrain with only the regional slope and escarpment (cheap; for checks)."""
    resolution = 65
    axis = np.linspace(-config.extent_m / 2, config.extent_m / 2, resolution)
    azimuth = math.radians(config.slope_azimuth_deg)
    uphill = axis[None, :] * math.cos(azimuth) + axis[:, None] * math.sin(azimuth)
    heights = math.tan(math.radians(config.slope_deg)) * uphill
    if config.scarp_height_m > 0:
        heights = heights + 0.5 * config.scarp_height_m * np.tanh((uphill - config.scarp_offset_m) / (0.5 * config.scarp_width_m))
    return Terrain(heights=heights.astype(np.float32), extent_m=config.extent_m,
                   sand_mask=np.zeros_like(heights, dtype=np.float32))


def views_beyond_terrain(poses: list[CameraPose], terrain: Terrain, margin_fraction: float = 0.0) -> list[str]:
    """Names of views whose image border sees no ground inside the square (sky, or past the edge).

    ``margin_fraction`` shrinks the accepted square (0.03 = hits within 97% of it).
    """
    if not poses:
        return []
    origins, directions, owners = [], [], []
    for index, pose in enumerate(poses):
        rays = pose.pixel_rays(pose.border_pixels())
        origins.append(np.repeat(pose.camera_center[None, :], rays.shape[0], axis=0))
        directions.append(rays)
        owners.extend([index] * rays.shape[0])
    origins_array, directions_array = np.concatenate(origins), np.concatenate(directions)
    distances = terrain.raycast(origins_array, directions_array)
    hits = origins_array + np.where(np.isfinite(distances), distances, 0.0)[:, None] * directions_array
    limit = (1.0 - margin_fraction) * terrain.extent_m / 2
    bad = ~np.isfinite(distances) | (np.abs(hits[:, 0]) > limit) | (np.abs(hits[:, 1]) > limit)
    return sorted({poses[owner].name for owner, is_bad in zip(owners, bad) if is_bad})


def horizon_problem(rig: RigConfig, render: RenderConfig, terrain_config: TerrainConfig, seed: int = 0) -> str | None:
    """A sentence when some view of the rig would show the sky or the terrain's edge, else None.

    Checked on the large-scale shape only (regional slope and escarpment on a coarse grid),
    lowered by twice the relief amplitude and half the dune height, with a 3% margin at the
    edge: cheap enough for ``SceneConfig.validate`` and on the safe side for real relief.
    """
    terrain = _large_scale_terrain(terrain_config)
    poses = make_camera_rig(rig, render, terrain, seed=seed)
    # The real ground wanders about the large-scale shape; where it dips, grazing rays
    # reach further. Testing against a copy lowered by ~two standard deviations of the
    # relief (and half the dune height) keeps the check on the safe side.
    drop = 2.0 * terrain_config.relief_amplitude_m + 0.5 * terrain_config.dune_amplitude_m
    lowered = dataclasses.replace(terrain, heights=terrain.heights - np.float32(drop))
    bad = views_beyond_terrain(poses, lowered, margin_fraction=0.03)
    if not bad:
        return None
    pitch = f", rig.pitch_deg={rig.pitch_deg}" if rig.kind in ("rover_traverse", "station_panorama", "aerial_oblique") else ""
    shown = ", ".join(bad[:3]) + (f" and {len(bad) - 3} more" if len(bad) > 3 else "")
    return (f"{len(bad)} of {len(poses)} views ({shown}) would see the sky or past the terrain edge "
            f"with rig.kind={rig.kind}{pitch}, a {render.vertical_fov_deg:.1f} deg "
            f"vertical field of view and terrain.extent_m={terrain_config.extent_m}")
