"""Scenes rendered from an external mesh: settings and camera rigs (numpy only, no bpy).

The Blender side (:mod:`esgs.esgs_addon.mesh_scene`) imports the mesh, builds a ray caster
on it and calls :func:`make_mesh_rig`; everything here only needs that ray caster, a
function ``cast(origins [N, 3], directions [N, 3]) -> distances [N]`` (``inf`` where a ray
misses), so the rigs can be tested on any surface.

World frame: the mesh's own frame as Blender has it after import (glTF +Y up becomes
+Z up), units of the file (metres for the Mars landform). Rigs (``MeshRigConfig.kind``):

* ``traverse``: a rover-like drive at mast height above the surface found by ray casting,
  ``spacing_m`` between views along a gently turning straight line, looking forward and
  tilted down by ``pitch_deg``. Start and heading are drawn from the seed; a draw is kept
  only when every position lies at least ``border_margin_m`` inside the mesh outline and
  every probe ray through the image (a grid including the corners) meets the surface, so
  no view looks past the edge or at the sky.
* ``orbit``: an arc of ``sweep_deg`` around a centre (default: the middle of the mesh's
  footprint), ``orbit_radius_m`` away and ``orbit_height_m`` above the surface there,
  every view aimed at the centre's surface point, with the same probe test.
* ``mixed``: an aerial ``orbit`` (the first ``views - rover_views`` views) and a rover
  ``traverse`` at mast height that starts inside the orbit's circle (the last
  ``rover_views``), pitched ``rover_pitch_deg`` so that the horizon and the sky are in frame:
  a rover view must meet the surface with every probe ray of the lower half of the image that
  points more than 5 degrees below the horizon, and the drive is kept when at least
  ``min_sky_fraction`` of its probe rays (all rover views together) reach the sky. With
  enough views (36: every 8th held out) the held-out views include aerial and rover ones.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ..errors import ConfigError, DatasetError
from .config import RenderConfig
from .rigs import CameraPose, intrinsics, pose_matrix

#: Mesh file types the Blender side can import.
MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply")
MESH_RIG_KINDS = ("traverse", "orbit", "mixed")
_STREAM_MESH_RIG = 0x4D657368

RayCaster = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _help(text: str, **extra) -> dict:
    return {"help": text, **extra}


@dataclass
class MeshRigConfig:
    """Camera layout over an external mesh (see the module docstring)."""

    kind: str = field(default="traverse", metadata=_help("camera layout", choices=MESH_RIG_KINDS))
    views: int = field(default=10, metadata=_help("number of camera views"))
    mast_height_m: float = field(default=2.0, metadata=_help("traverse: camera height above the surface below it"))
    pitch_deg: float = field(default=-30.0, metadata=_help("traverse: camera elevation, degrees (negative looks down)"))
    spacing_m: float = field(default=1.0, metadata=_help("traverse: distance between consecutive views"))
    max_turn_deg: float = field(default=3.0, metadata=_help("traverse: largest change of heading between views"))
    border_margin_m: float = field(default=20.0, metadata=_help("traverse: camera positions stay this far inside the mesh outline"))
    orbit_radius_m: float = field(default=0.0, metadata=_help("orbit: horizontal distance from the centre (0 = 10 % of the footprint's smaller side)"))
    orbit_height_m: float = field(default=0.0, metadata=_help("orbit: height above the centre's surface (0 = 0.6 x radius)"))
    sweep_deg: float = field(default=90.0, metadata=_help("orbit: azimuth covered by the arc, degrees"))
    center_x_m: Optional[float] = field(default=None, metadata=_help("orbit: centre x (None = middle of the footprint)"))
    center_y_m: Optional[float] = field(default=None, metadata=_help("orbit: centre y (None = middle of the footprint)"))
    rover_views: int = field(default=0, metadata=_help("mixed: how many views are rover-height views (0 = 40 % of views)"))
    rover_pitch_deg: float = field(default=2.0, metadata=_help("mixed: rover views' pitch, degrees (near 0 shows the horizon)"))
    min_sky_fraction: float = field(default=0.1, metadata=_help("mixed: least share of the rover views' probe rays that reach the sky"))
    min_clearance_m: float = field(default=1.0, metadata=_help("cameras stay at least this high above the surface below them"))
    probe_grid: int = field(default=9, metadata=_help("probe rays per image row and column when checking a view (corners included)"))
    max_attempts: int = field(default=300, metadata=_help("random placements tried before giving up"))

    def validate(self) -> None:
        def need(condition: bool, name: str, message: str) -> None:
            if not condition:
                raise ConfigError(f"rig.{name} {message}, got {getattr(self, name)!r}")

        need(self.kind in MESH_RIG_KINDS, "kind", f"must be one of {', '.join(MESH_RIG_KINDS)}")
        need(isinstance(self.views, int) and self.views >= 1, "views", "must be a positive integer")
        need(self.mast_height_m > 0, "mast_height_m", "must be positive")
        need(-89.0 <= self.pitch_deg <= 89.0, "pitch_deg", "must be between -89 and 89 degrees")
        need(self.spacing_m > 0, "spacing_m", "must be positive")
        need(0 <= self.max_turn_deg <= 45, "max_turn_deg", "must be between 0 and 45 degrees")
        need(self.border_margin_m >= 0, "border_margin_m", "must not be negative")
        need(self.orbit_radius_m >= 0, "orbit_radius_m", "must not be negative (0 = automatic)")
        need(self.orbit_height_m >= 0, "orbit_height_m", "must not be negative (0 = automatic)")
        need(0 < self.sweep_deg <= 360, "sweep_deg", "must be in (0, 360] degrees")
        need(isinstance(self.rover_views, int) and self.rover_views >= 0, "rover_views", "must not be negative")
        need(-89.0 <= self.rover_pitch_deg <= 89.0, "rover_pitch_deg", "must be between -89 and 89 degrees")
        need(0.0 <= self.min_sky_fraction < 0.5, "min_sky_fraction", "must be in [0, 0.5)")
        if self.kind == "mixed":
            need(self.views >= 4, "views", "must be at least 4 for a mixed rig")
            need(self.rover_views < self.views, "rover_views", "must be below views (0 = automatic)")
        need(self.min_clearance_m >= 0, "min_clearance_m", "must not be negative")
        need(self.probe_grid >= 2, "probe_grid", "must be at least 2")
        need(self.max_attempts >= 1, "max_attempts", "must be at least 1")


def _default_render() -> RenderConfig:
    return RenderConfig(width=960, height=540, samples=16, fov_deg=60.0)


@dataclass
class MeshSceneConfig:
    """Everything that defines a scene rendered from an external mesh; with ``seed`` it is reproducible.

    Duck-types the parts of the synthetic SceneConfig that rendering and export read
    (``name``, ``seed``, ``rig.views``, ``render``).
    """

    mesh: str = field(default="", metadata=_help("mesh file (.glb, .gltf, .obj, .ply)"))
    name: str = field(default="mesh", metadata=_help("scene name (default: the mesh file's stem)"))
    seed: int = field(default=0, metadata=_help("random seed of the camera rig (non-negative)"))
    rig: MeshRigConfig = field(default_factory=MeshRigConfig)
    render: RenderConfig = field(default_factory=_default_render)

    def validate(self) -> None:
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed must be a non-negative integer, got {self.seed!r}")
        self.rig.validate()
        self.render.validate()
        check_mesh_file(self.mesh)


def check_mesh_file(path: str | Path) -> Path:
    """The mesh path, resolved; :class:`DatasetError` naming the file when it cannot be used."""
    if not str(path):
        raise ConfigError("no mesh file given", hint="pass --mesh PATH (.glb, .gltf, .obj or .ply)")
    path = Path(path).expanduser()
    if not path.is_file():
        raise DatasetError("mesh file not found", path=path, hint="check the path given with --mesh")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DatasetError(f"unsupported mesh file type {path.suffix!r}", path=path,
                           hint=f"use one of {', '.join(MESH_SUFFIXES)}")
    if path.stat().st_size == 0:
        raise DatasetError("mesh file is empty", path=path)
    return path.resolve()


@dataclass
class Footprint:
    """The mesh seen from above on a regular grid: where it is and how high (top surface).

    heights: [R, C] surface height (NaN outside the mesh) at ``x = x0 + col * cell``,
    ``y = y0 + row * cell``; inside_distance: [R, C] distance to the outline (0 outside).
    """

    x0: float
    y0: float
    cell: float
    heights: np.ndarray
    inside_distance: np.ndarray

    def lookup(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(nearest-cell inside_distance [N], inside [N]) at points xy [N, 2]; outside the grid counts as 0."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        col = np.rint((xy[:, 0] - self.x0) / self.cell).astype(np.int64)
        row = np.rint((xy[:, 1] - self.y0) / self.cell).astype(np.int64)
        rows, cols = self.heights.shape
        ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        distance = np.zeros(len(xy))
        distance[ok] = self.inside_distance[row[ok], col[ok]]
        return distance, ok & (distance > 0)


def surface_below(cast: RayCaster, xy: np.ndarray, top_z: float) -> np.ndarray:
    """Height [N] of the highest surface below points xy [N, 2] (NaN where there is none)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    origins = np.concatenate([xy, np.full((len(xy), 1), float(top_z))], axis=1)
    directions = np.tile(np.array([0.0, 0.0, -1.0]), (len(xy), 1))
    distances = np.asarray(cast(origins, directions), dtype=np.float64)
    return np.where(np.isfinite(distances), top_z - distances, np.nan)


def mesh_footprint(cast: RayCaster, bounds_min: np.ndarray, bounds_max: np.ndarray, cells: int = 200) -> Footprint:
    """Cast rays straight down on a grid over the bounds (``cells`` along the longer side)."""
    from scipy.ndimage import distance_transform_edt

    bounds_min, bounds_max = np.asarray(bounds_min, float), np.asarray(bounds_max, float)
    size = bounds_max[:2] - bounds_min[:2]
    cell = float(max(size.max(), 1e-6) / cells)
    cols, rows = (np.floor(size / cell).astype(int) + 1)
    x, y = np.meshgrid(bounds_min[0] + cell * np.arange(cols), bounds_min[1] + cell * np.arange(rows))
    top = float(bounds_max[2] + max(1.0, 0.01 * size.max()))
    heights = surface_below(cast, np.stack([x.ravel(), y.ravel()], axis=1), top).reshape(rows, cols)
    inside = np.isfinite(heights)
    # a grid padded with "outside" so the bounding box edge counts as outline too
    padded = np.pad(inside, 1, constant_values=False)
    distance = distance_transform_edt(padded)[1:-1, 1:-1] * cell
    return Footprint(float(bounds_min[0]), float(bounds_min[1]), cell, heights, np.where(inside, distance, 0.0))


def _probe_pixels(width: int, height: int, grid: int) -> np.ndarray:
    """Pixel coordinates [grid * grid, 2] over the whole image, border pixels' centres included."""
    u = np.linspace(0.5, width - 0.5, grid)
    v = np.linspace(0.5, height - 0.5, grid)
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def _views_see_surface(poses: list[CameraPose], cast: RayCaster, grid: int, min_distance: float) -> bool:
    """True when every probe ray of every view meets the surface farther than ``min_distance``."""
    origins, directions = [], []
    for pose in poses:
        rays = pose.pixel_rays(_probe_pixels(pose.width, pose.height, grid))
        origins.append(np.repeat(pose.camera_center[None], len(rays), axis=0))
        directions.append(rays)
    distances = np.asarray(cast(np.concatenate(origins), np.concatenate(directions)), dtype=np.float64)
    return bool(np.all(np.isfinite(distances) & (distances > min_distance)))


def _poses(positions: np.ndarray, yaws: np.ndarray, pitches: np.ndarray, render: RenderConfig) -> list[CameraPose]:
    K = intrinsics(render)
    return [CameraPose(name=f"view_{index:03d}", K=K.copy(),
                       world_to_camera=pose_matrix(positions[index], float(yaws[index]), float(pitches[index])),
                       width=render.width, height=render.height)
            for index in range(len(positions))]


def make_mesh_rig(rig: MeshRigConfig, render: RenderConfig, cast: RayCaster, bounds_min: np.ndarray,
                  bounds_max: np.ndarray, *, seed: int = 0, source: str | Path | None = None) -> list[CameraPose]:
    """Camera poses [rig.views] over a mesh given by its ray caster and bounds [3] (deterministic for ``seed``).

    Raises :class:`DatasetError` (naming ``source``) when no placement passes the checks
    within ``rig.max_attempts`` draws, with a hint on which setting to change.
    """
    rig.validate()
    render.validate()
    rng = np.random.default_rng([int(seed), _STREAM_MESH_RIG])
    footprint = mesh_footprint(cast, bounds_min, bounds_max)
    if not np.isfinite(footprint.heights).any():
        raise DatasetError("no surface found when looking down on the mesh from above", path=source,
                           hint="the rigs need a terrain-like mesh with +Z up after import")
    top_z = float(np.asarray(bounds_max, float)[2] + max(1.0, footprint.cell))
    if rig.kind == "traverse":
        poses = _traverse(rig, render, cast, footprint, top_z, rng)
        hint = ("lower --views / rig.spacing_m or rig.border_margin_m, or raise rig.pitch_deg downwards "
                "(views must see the surface in every direction)")
    elif rig.kind == "mixed":
        poses = _mixed(rig, render, cast, footprint, top_z, rng)
        hint = ("change rig.rover_pitch_deg (up shows more sky, down more ground), lower rig.min_sky_fraction, "
                "lower rig.border_margin_m, or change the orbit (rig.orbit_radius_m, the centre: esgs scene "
                "--site-center X,Y)")
    else:
        poses = _orbit(rig, render, cast, footprint, top_z, rng)
        hint = "change rig.orbit_radius_m, rig.orbit_height_m or the centre (esgs scene --site-center X,Y)"
    if poses is None:
        needs = ("aerial views must see only surface; rover views must see the ground below the horizon "
                 "and the sky above it" if rig.kind == "mixed" else "every view must see only surface")
        raise DatasetError(f"could not place {rig.views} '{rig.kind}' cameras over the mesh in {rig.max_attempts} "
                           f"attempts (every view must stay inside the outline; {needs})",
                           path=source, hint=hint)
    return poses


def _traverse(rig: MeshRigConfig, render: RenderConfig, cast: RayCaster, footprint: Footprint, top_z: float,
              rng: np.random.Generator, *, views: Optional[int] = None, pitch_deg: Optional[float] = None,
              region: Optional[np.ndarray] = None, sky: bool = False) -> list[CameraPose] | None:
    """A drive of ``views`` (default rig.views) at ``pitch_deg`` (default rig.pitch_deg), started
    in ``region`` (a footprint-shaped boolean grid; default everywhere). ``sky``: the views
    need the surface along the lower half of the image only, and the drive is kept when at
    least ``rig.min_sky_fraction`` of the probe rays miss the mesh."""
    views = rig.views if views is None else views
    allowed = footprint.inside_distance >= max(rig.border_margin_m, footprint.cell)
    if region is not None:
        allowed &= region
    candidates = np.argwhere(allowed)
    if len(candidates) == 0:
        return None
    pitch = math.radians(rig.pitch_deg if pitch_deg is None else pitch_deg)
    for _ in range(rig.max_attempts):
        row, col = candidates[rng.integers(len(candidates))]
        start = np.array([footprint.x0 + col * footprint.cell, footprint.y0 + row * footprint.cell])
        heading0 = rng.uniform(0.0, 2.0 * math.pi)
        turns = rng.uniform(-1.0, 1.0, size=views) * math.radians(rig.max_turn_deg)
        turns[0] = 0.0
        headings = heading0 + np.cumsum(turns)
        steps = rig.spacing_m * np.stack([np.cos(headings), np.sin(headings)], axis=1)
        xy = start + np.concatenate([np.zeros((1, 2)), np.cumsum(steps[:-1], axis=0)])
        # centre the drive on the drawn point so the margin test treats both ends alike
        xy -= xy.mean(axis=0) - start
        distance, inside = footprint.lookup(xy)
        if not np.all(inside & (distance >= rig.border_margin_m)):
            continue
        ground = surface_below(cast, xy, top_z)
        if not np.all(np.isfinite(ground)):
            continue
        positions = np.concatenate([xy, (ground + rig.mast_height_m)[:, None]], axis=1)
        poses = _poses(positions, headings, np.full(views, pitch), render)
        if sky:
            fraction = _sky_fraction(poses, cast, rig.probe_grid, render.near_m)
            if fraction is None or fraction < rig.min_sky_fraction:
                continue
        elif not _views_see_surface(poses, cast, rig.probe_grid, render.near_m):
            continue
        for pose in poses:
            pose.target = _central_hit(pose, cast)
        return poses
    return None


#: a rover view's probe rays this far below the horizon must meet the surface (5 degrees: within
#: 23 m of a 2 m mast on flat ground; rays nearer the horizon may pass the mesh's far edge)
_GROUND_RAY_MIN_DEPRESSION = math.sin(math.radians(5.0))


def _sky_fraction(poses: list[CameraPose], cast: RayCaster, grid: int, min_distance: float) -> Optional[float]:
    """Share of the probe rays of ``poses`` that miss the mesh, or None when a ray of the lower
    half of an image that points more than 5 degrees below the horizon misses it, or when
    any ray meets it nearer than ``min_distance``."""
    pixels = _probe_pixels(poses[0].width, poses[0].height, grid)
    lower = pixels[:, 1] >= poses[0].height / 2
    missed = 0
    for pose in poses:
        rays = pose.pixel_rays(pixels)
        distances = np.asarray(cast(np.repeat(pose.camera_center[None], len(rays), axis=0), rays), dtype=np.float64)
        hit = np.isfinite(distances)
        ground = lower & (rays[:, 2] < -_GROUND_RAY_MIN_DEPRESSION)
        if not np.all(hit[ground]) or np.any(distances[hit] <= min_distance):
            return None
        missed += int((~hit).sum())
    return missed / (len(poses) * len(pixels))


def _mixed(rig: MeshRigConfig, render: RenderConfig, cast: RayCaster, footprint: Footprint, top_z: float,
           rng: np.random.Generator) -> list[CameraPose] | None:
    """Aerial orbit views, then rover views with sky driving inside the orbit's circle."""
    import dataclasses

    rover_views = rig.rover_views or max(1, round(0.4 * rig.views))
    aerial = _orbit(dataclasses.replace(rig, kind="orbit", views=rig.views - rover_views), render, cast,
                    footprint, top_z, rng)
    if aerial is None:
        return None
    centre = aerial[0].target[:2]
    radius = float(np.linalg.norm(aerial[0].camera_center[:2] - centre))
    rows, cols = footprint.heights.shape
    x = footprint.x0 + footprint.cell * np.arange(cols)
    y = footprint.y0 + footprint.cell * np.arange(rows)
    region = np.hypot(x[None, :] - centre[0], y[:, None] - centre[1]) <= radius
    rover = _traverse(rig, render, cast, footprint, top_z, rng, views=rover_views, pitch_deg=rig.rover_pitch_deg,
                      region=region, sky=True)
    if rover is None:
        return None
    poses = aerial + rover
    for index, pose in enumerate(poses):
        pose.name = f"view_{index:03d}"
    return poses


def _orbit(rig: MeshRigConfig, render: RenderConfig, cast: RayCaster, footprint: Footprint, top_z: float,
           rng: np.random.Generator) -> list[CameraPose] | None:
    inside = np.argwhere(np.isfinite(footprint.heights))
    rows, cols = footprint.heights.shape
    if rig.center_x_m is None or rig.center_y_m is None:
        middle = inside.mean(axis=0)
        centre_xy = np.array([footprint.x0 + middle[1] * footprint.cell, footprint.y0 + middle[0] * footprint.cell])
    else:
        centre_xy = np.array([rig.center_x_m, rig.center_y_m], dtype=np.float64)
    centre_z = surface_below(cast, centre_xy[None], top_z)[0]
    if not np.isfinite(centre_z):
        return None
    target = np.array([*centre_xy, centre_z])
    radius = rig.orbit_radius_m or 0.1 * footprint.cell * min(rows, cols)
    height = rig.orbit_height_m or 0.6 * radius
    full_circle = rig.sweep_deg >= 360.0
    fractions = np.arange(rig.views) / (rig.views if full_circle else max(rig.views - 1, 1))
    for _ in range(rig.max_attempts):
        azimuths = rng.uniform(0.0, 2.0 * math.pi) + math.radians(rig.sweep_deg) * fractions
        xy = centre_xy + radius * np.stack([np.cos(azimuths), np.sin(azimuths)], axis=1)
        ground = surface_below(cast, xy, top_z)
        if not np.all(np.isfinite(ground)):
            continue
        z = np.maximum(centre_z + height, ground + rig.min_clearance_m)
        positions = np.concatenate([xy, z[:, None]], axis=1)
        offsets = target - positions
        yaws = np.arctan2(offsets[:, 1], offsets[:, 0])
        pitches = np.arctan2(offsets[:, 2], np.linalg.norm(offsets[:, :2], axis=1))
        poses = _poses(positions, yaws, pitches, render)
        if not _views_see_surface(poses, cast, rig.probe_grid, render.near_m):
            continue
        # the centre must not be hidden behind nearer relief
        hits = [_central_hit(pose, cast) for pose in poses]
        if all(np.isfinite(hit).all() and np.linalg.norm(hit - target) <= 0.02 * np.linalg.norm(offset)
               for hit, offset in zip(hits, offsets)):
            for pose in poses:
                pose.target = target.copy()
            return poses
    return None


def _central_hit(pose: CameraPose, cast: RayCaster) -> np.ndarray:
    """World point [3] where the view's central ray meets the surface (NaN when it does not)."""
    direction = pose.forward
    distance = float(np.asarray(cast(pose.camera_center[None], direction[None]))[0])
    return pose.camera_center + distance * direction if np.isfinite(distance) else np.full(3, np.nan)
