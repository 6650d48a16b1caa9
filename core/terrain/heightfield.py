"""The terrain: a square heightfield plus crater, rock and sand tables, and its generator.

Grid convention (used by every consumer, e.g. the Blender mesh builder):

* ``heights[i, j]`` is the ground height (metres, +Z up) at
  ``x = -extent_m / 2 + j * cell_m`` and ``y = -extent_m / 2 + i * cell_m``:
  columns run along +x (east), rows along +y (north). Row 0 is the southern edge
  (y = -extent_m / 2); shown as an image with the origin at the top, north is down.
* ``cell_m = extent_m / (resolution - 1)``: the grid includes both edges, so the corner
  samples sit exactly on the square's corners and, for odd resolutions, one on the origin.
* Rocks are separate objects: ``heights`` is the ground without them.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..errors import ConfigError, DatasetError, FormatError
from ..progress import ProgressCallback, ProgressEvent
from .config import TerrainConfig
from .craters import apply_craters, sample_craters
from .dunes import dune_component, sand_mask
from .noise import fractal_noise
from .rocks import place_rocks

# Independent random streams per component: changing, say, the crater count leaves the
# relief, sand and rocks of the same seed untouched.
_STREAM_RELIEF, _STREAM_CRATERS, _STREAM_SAND, _STREAM_DUNES, _STREAM_ROCKS = range(1, 6)


def component_rng(seed: int, stream: int) -> np.random.Generator:
    """The random generator of one terrain component for ``seed``."""
    return np.random.default_rng([int(seed), int(stream)])


@dataclass(eq=False)  # arrays: compare fields explicitly (np.array_equal), not with ==
class Terrain:
    """A generated terrain. See the module docstring for the grid convention.

    heights: [R, R] float32 metres. sand_mask: [R, R] float32 in [0, 1] (1 = sand).
    craters: [K, 5] float64 (x, y, diameter_m, depth_m, degradation).
    rocks: [M, 7] float64 (x, y, z_base, diameter_m, height_m, yaw_rad, shape_seed).
    components: named [R, R] float32 layers that add up to ``heights`` ("relief",
    "craters", "layers", "sand_fill", "dunes"), kept for analysis and tests.
    """

    heights: np.ndarray
    extent_m: float
    sand_mask: np.ndarray
    craters: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    rocks: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    components: dict[str, np.ndarray] = field(default_factory=dict)
    _gradient: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    @property
    def resolution(self) -> int:
        return int(self.heights.shape[0])

    @property
    def cell_m(self) -> float:
        """Distance between neighbouring samples, metres."""
        return self.extent_m / (self.resolution - 1)

    @property
    def coordinates(self) -> tuple[np.ndarray, np.ndarray]:
        """x of the columns [R] and y of the rows [R], metres."""
        axis = np.linspace(-self.extent_m / 2, self.extent_m / 2, self.resolution)
        return axis, axis.copy()

    def contains(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Whether points lie inside the terrain square (bool array shaped like x)."""
        half = self.extent_m / 2
        return (np.abs(np.asarray(x)) <= half) & (np.abs(np.asarray(y)) <= half)

    def _grid_position(self, x: np.ndarray, y: np.ndarray):
        last = self.resolution - 1
        col = np.clip((np.asarray(x, dtype=np.float64) + self.extent_m / 2) / self.cell_m, 0.0, last)
        row = np.clip((np.asarray(y, dtype=np.float64) + self.extent_m / 2) / self.cell_m, 0.0, last)
        col0 = np.minimum(np.floor(col).astype(np.int64), last - 1)
        row0 = np.minimum(np.floor(row).astype(np.int64), last - 1)
        return row0, col0, row - row0, col - col0

    def _bilinear(self, grid: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        row0, col0, fr, fc = self._grid_position(x, y)
        g = grid
        top = g[row0, col0] * (1 - fc) + g[row0, col0 + 1] * fc
        bottom = g[row0 + 1, col0] * (1 - fc) + g[row0 + 1, col0 + 1] * fc
        return top * (1 - fr) + bottom * fr

    def height_at(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Bilinearly interpolated ground height at world (x, y), metres; clamped at the edges.

        x, y: any broadcast-compatible shapes; returns float64 of that shape.
        """
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return self._bilinear(self.heights.astype(np.float64, copy=False), x, y)

    def gradient(self) -> tuple[np.ndarray, np.ndarray]:
        """dh/dx [R, R] and dh/dy [R, R] by central differences (one-sided at the edges)."""
        if self._gradient is None:
            d_rows, d_cols = np.gradient(self.heights.astype(np.float64), self.cell_m)
            self._gradient = (d_cols, d_rows)
        return self._gradient

    def normal_at(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Unit upward surface normals at world (x, y): shape (*broadcast(x, y).shape, 3)."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        d_x, d_y = self.gradient()
        gx = self._bilinear(d_x, x, y)
        gy = self._bilinear(d_y, x, y)
        normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        return normal / np.linalg.norm(normal, axis=-1, keepdims=True)

    def raycast(self, origins: np.ndarray, directions: np.ndarray, max_distance_m: float | None = None) -> np.ndarray:
        """Distance along each ray to the first ground hit inside the square; inf where none.

        origins: [N, 3], directions: [N, 3] (normalised here). Marches in half-cell steps and
        refines the crossing linearly; rays that leave the square before hitting miss.
        Rocks are not included.
        """
        origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        if max_distance_m is None:
            relief = float(self.heights.max() - self.heights.min())
            max_distance_m = 1.5 * self.extent_m + relief + float(np.abs(origins[:, 2]).max(initial=0.0))
        step = 0.5 * self.cell_m
        steps = np.arange(0.0, max_distance_m + step, step)
        result = np.full(origins.shape[0], np.inf)
        chunk = max(1, 2_000_000 // steps.size)
        for start in range(0, origins.shape[0], chunk):
            o = origins[start:start + chunk, None, :]
            d = directions[start:start + chunk, None, :]
            points = o + d * steps[None, :, None]
            inside = self.contains(points[..., 0], points[..., 1])
            above = points[..., 2] - self.height_at(points[..., 0], points[..., 1])
            hit = inside & (above <= 0)
            any_hit = hit.any(axis=1)
            rows = np.nonzero(any_hit)[0]
            first = np.argmax(hit, axis=1)[rows]
            previous = np.maximum(first - 1, 0)
            a, b = above[rows, previous], above[rows, first]
            with np.errstate(divide="ignore", invalid="ignore"):
                fraction = np.where(a != b, np.clip(a / (a - b), 0.0, 1.0), 0.0)
            distance = steps[previous] + fraction * step
            # Starting below the ground: distance 0. Entering the square already below the
            # ground: the ray meets the square's edge wall.
            distance = np.where(first == 0, 0.0, distance)
            distance = np.where((first > 0) & ~inside[rows, previous], steps[first], distance)
            result[start + rows] = distance
        return result


def _report(progress: ProgressCallback | None, step: int, total: int, message: str) -> None:
    if progress is not None:
        progress(ProgressEvent(step=step, total=total, stage="terrain", message=message))


def _terrace(heights: np.ndarray, thickness: float, sharpness: float) -> np.ndarray:
    """Step-like layering: flat treads and steep risers every ``thickness`` metres."""
    level = heights / thickness
    base = np.floor(level)
    exponent = 1.0 + 9.0 * sharpness
    return thickness * (base + (level - base) ** exponent)


def generate_terrain(config: TerrainConfig, seed: int = 0, *, progress: ProgressCallback | None = None) -> Terrain:
    """Build the terrain of ``config`` for ``seed`` (deterministic: same inputs, same arrays).

    Order: fractal relief + regional slope + escarpment, craters, layer terraces, sand
    cover (low ground and noise patches, smoothing the bedrock under it), dunes and
    ripples on the sand, then rocks on the final surface. Raises ConfigError on bad config.
    """
    config.validate()
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ConfigError(f"seed must be a non-negative integer (got {seed!r})")
    total = 5
    resolution, extent = config.resolution, config.extent_m
    cell = config.cell_m
    axis = np.linspace(-extent / 2, extent / 2, resolution)
    components: dict[str, np.ndarray] = {}

    _report(progress, 0, total, "relief")
    relief = np.zeros((resolution, resolution))
    if config.relief_amplitude_m > 0:
        relief += config.relief_amplitude_m * fractal_noise(
            axis, axis, component_rng(seed, _STREAM_RELIEF), wavelength_m=config.relief_wavelength_m,
            octaves=config.relief_octaves, roughness=config.relief_roughness, ridged=config.ridged_fraction,
            min_wavelength_m=2 * cell)
    azimuth = np.radians(config.slope_azimuth_deg)
    uphill = axis[None, :] * np.cos(azimuth) + axis[:, None] * np.sin(azimuth)
    relief += np.tan(np.radians(config.slope_deg)) * uphill
    if config.scarp_height_m > 0:
        relief += 0.5 * config.scarp_height_m * np.tanh((uphill - config.scarp_offset_m) / (0.5 * config.scarp_width_m))
    components["relief"] = relief.astype(np.float32)
    heights = relief.copy()

    _report(progress, 1, total, "craters")
    craters = sample_craters(config, component_rng(seed, _STREAM_CRATERS))
    apply_craters(heights, craters, extent, config.crater_rim_ratio)
    components["craters"] = (heights - relief).astype(np.float32)

    if config.layer_thickness_m > 0:
        terraced = _terrace(heights, config.layer_thickness_m, config.layer_sharpness)
        # Beds show where erosion cuts through them (slopes, scarps, crater walls); gentle
        # ground keeps its cap surface instead of turning into contour-line steps.
        d_rows, d_cols = np.gradient(ndimage.gaussian_filter(heights, sigma=max(1.0 / cell, 1.0)), cell)
        slope = np.hypot(d_rows, d_cols)
        exposure = np.clip((slope - 0.08) / 0.25, 0.0, 1.0)
        exposure = exposure * exposure * (3.0 - 2.0 * exposure)
        layered = heights + exposure * (terraced - heights)
        components["layers"] = (layered - heights).astype(np.float32)
        heights = layered

    _report(progress, 2, total, "sand")
    sand = sand_mask(config, heights, axis, axis, component_rng(seed, _STREAM_SAND))
    if sand.max() > 0:
        # Sand drapes the bedrock: it fills small hollows and buries terrace steps.
        draped = ndimage.gaussian_filter(heights, sigma=max(1.0 / cell, 0.5), mode="nearest")
        fill = 0.8 * sand * (draped - heights)
        components["sand_fill"] = fill.astype(np.float32)
        heights = heights + fill

    _report(progress, 3, total, "dunes")
    dunes = dune_component(config, axis, axis, component_rng(seed, _STREAM_DUNES))
    if dunes.any():
        masked = sand * dunes
        components["dunes"] = masked.astype(np.float32)
        heights = heights + masked

    terrain = Terrain(heights=heights.astype(np.float32), extent_m=float(extent),
                      sand_mask=sand.astype(np.float32), craters=craters, components=components)
    _report(progress, 4, total, "rocks")
    if config.rock_abundance > 0:
        terrain.rocks = place_rocks(config, terrain, component_rng(seed, _STREAM_ROCKS))
    _report(progress, total, total, "done")
    return terrain


def replace_terrain(terrain: Terrain, **changes) -> Terrain:
    """A copy of ``terrain`` with some fields replaced (cached gradients are dropped)."""
    return dataclasses.replace(terrain, _gradient=None, **changes)


_SAVED_ARRAYS = ("heights", "sand_mask", "craters", "rocks")


def save_terrain(terrain: Terrain, path: str | Path, *, include_components: bool = False) -> None:
    """Write a terrain to a ``.npz`` file atomically (arrays exactly as generated).

    Regenerating from the scene config and seed gives the same arrays; the file is for
    tools that want the ground truth without this package's generator.
    """
    import io

    from ..io_utils import atomic_write_bytes

    arrays = {name: getattr(terrain, name) for name in _SAVED_ARRAYS}
    arrays["extent_m"] = np.float64(terrain.extent_m)
    if include_components:
        arrays.update({f"component_{name}": layer for name, layer in terrain.components.items()})
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    atomic_write_bytes(path, buffer.getvalue())


def load_terrain(path: str | Path) -> Terrain:
    """Read a terrain written by :func:`save_terrain`; FormatError when the file is not one."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError("terrain file not found", path=path)
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [name for name in (*_SAVED_ARRAYS, "extent_m") if name not in data]
            if missing:
                raise FormatError(f"not a terrain file: missing {', '.join(missing)}", path=path,
                                  hint="write it with esgs.core.terrain.save_terrain")
            arrays = {name: data[name] for name in _SAVED_ARRAYS}
            extent = float(data["extent_m"])
            components = {name[len("component_"):]: data[name] for name in data.files if name.startswith("component_")}
    except (OSError, ValueError) as err:
        raise FormatError(f"cannot read terrain file: {err}", path=path) from err
    heights = arrays["heights"]
    if heights.ndim != 2 or heights.shape[0] != heights.shape[1] or heights.shape[0] < 2 or arrays["sand_mask"].shape != heights.shape:
        raise FormatError(f"heights/sand_mask must be square and equal in shape, got {heights.shape} and "
                          f"{arrays['sand_mask'].shape}", path=path)
    if arrays["craters"].ndim != 2 or arrays["craters"].shape[1] != 5 or arrays["rocks"].ndim != 2 or arrays["rocks"].shape[1] != 7:
        raise FormatError("craters must be [K, 5] and rocks [M, 7]", path=path)
    return Terrain(heights=heights, extent_m=extent, sand_mask=arrays["sand_mask"], craters=arrays["craters"],
                   rocks=arrays["rocks"], components=components)
