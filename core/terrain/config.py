"""Settings of a synthetic Mars scene: terrain, camera rig, render camera, light.

Conventions used by every field (see docs/terrain.md):

* World frame: metres, ``+Z`` up, ``x`` east, ``y`` north, terrain centred on the origin.
* Azimuths (``sun_azimuth_deg``, ``wind_azimuth_deg``, ``heading_deg``...) are measured
  counter-clockwise from ``+x`` seen from above: 0 = +x, 90 = +y.
* Pitch / elevation angles are positive above the horizontal, negative below it.

Every dataclass has ``validate()`` which raises :class:`ConfigError` naming the field
(``terrain.resolution``, ``rig.views``...) so bad input fails before any heavy work.
"""
from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from typing import Any

from ..errors import ConfigError
from .rock_sizes import expected_rock_count

RIG_KINDS = ("rover_traverse", "station_panorama", "orbit", "aerial_oblique", "aerial_nadir")

# Camera presets: the values a RenderConfig takes when ``camera`` names one of them.
# MSL Navcam: 45 deg square field of view, 1024 x 1024 pixels, one (panchromatic) channel.
CAMERA_PRESETS: dict[str, dict[str, Any]] = {
    "navcam": {"width": 1024, "height": 1024, "fov_deg": 45.0, "grayscale": True},
    "generic_rgb": {"width": 960, "height": 540, "fov_deg": 60.0, "grayscale": False},
    "custom": {},
}


def _help(text: str, **extra: Any) -> dict[str, Any]:
    return {"help": text, **extra}


def _check_types(config: Any, section: str) -> None:
    """Reject values whose type does not match the annotation (TOML/JSON typos, CLI mixups)."""
    hints = typing.get_type_hints(type(config))
    for fld in dataclasses.fields(config):
        value = getattr(config, fld.name)
        annotation = hints[fld.name]
        where = f"{section}.{fld.name}" if section else fld.name
        if dataclasses.is_dataclass(annotation):
            if not isinstance(value, annotation):
                raise ConfigError(f"{where} must be a {annotation.__name__} table, got {type(value).__name__}")
            continue
        if annotation is bool:
            ok = isinstance(value, bool)
        elif annotation is int:
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif annotation is float:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        elif annotation is str:
            ok = isinstance(value, str)
        else:
            ok = True
        if not ok:
            raise ConfigError(f"{where} must be a finite {annotation.__name__}, got {value!r}")


def _require(condition: bool, where: str, message: str, value: Any) -> None:
    if not condition:
        raise ConfigError(f"{where} {message} (got {value!r})")


@dataclass
class TerrainConfig:
    """Heightfield, craters, rocks, sand and dunes. Lengths in metres, angles in degrees."""

    resolution: int = field(default=513, metadata=_help("samples per side of the square heightfield (odd keeps a node on the origin)"))
    extent_m: float = field(default=100.0, metadata=_help("side length of the square terrain, metres"))
    # Base relief: fractal (fBm) gradient noise, optionally ridged, plus a regional tilt.
    relief_amplitude_m: float = field(default=1.5, metadata=_help("standard deviation of the base relief, metres"))
    relief_wavelength_m: float = field(default=40.0, metadata=_help("wavelength of the coarsest relief octave, metres"))
    relief_octaves: int = field(default=6, metadata=_help("number of noise octaves (each half the wavelength of the previous)"))
    relief_roughness: float = field(default=0.5, metadata=_help("amplitude ratio between successive octaves (0..1; higher is rougher)"))
    ridged_fraction: float = field(default=0.0, metadata=_help("share of ridged noise in the base relief (0 = rounded hills, 1 = sharp ridges)"))
    slope_deg: float = field(default=0.0, metadata=_help("regional slope of the whole terrain, degrees"))
    slope_azimuth_deg: float = field(default=0.0, metadata=_help("direction the terrain rises toward (azimuth, ccw from +x)"))
    # Escarpment and layering (outcrops).
    scarp_height_m: float = field(default=0.0, metadata=_help("height of a straight escarpment across the terrain (0 = none)"))
    scarp_width_m: float = field(default=6.0, metadata=_help("horizontal width of the escarpment's steep face"))
    scarp_offset_m: float = field(default=0.0, metadata=_help("signed distance of the escarpment from the centre along slope_azimuth_deg"))
    layer_thickness_m: float = field(default=0.0, metadata=_help("thickness of exposed sedimentary layers, terraced into bedrock (0 = none)"))
    layer_sharpness: float = field(default=0.7, metadata=_help("how step-like the layer terraces are (0 = smooth, 1 = cliffs)"))
    # Impact craters: cumulative size-frequency N(>D) proportional to D^-b.
    crater_count: int = field(default=0, metadata=_help("number of craters with diameter in [crater_min_diameter_m, crater_max_diameter_m]"))
    crater_min_diameter_m: float = field(default=1.0, metadata=_help("smallest crater diameter, metres"))
    crater_max_diameter_m: float = field(default=30.0, metadata=_help("largest crater diameter, metres"))
    crater_sfd_exponent: float = field(default=2.0, metadata=_help("b in the cumulative size-frequency law N(>D) ~ D^-b"))
    crater_depth_ratio: float = field(default=0.2, metadata=_help("depth / diameter of a fresh crater"))
    crater_rim_ratio: float = field(default=0.04, metadata=_help("rim height / diameter of a fresh crater"))
    crater_degradation_min: float = field(default=0.0, metadata=_help("least degradation (0 = fresh, 1 = nearly erased)"))
    crater_degradation_max: float = field(default=1.0, metadata=_help("most degradation (0 = fresh, 1 = nearly erased)"))
    # Rocks: Golombek & Rapp cumulative fractional area F_k(D) = k exp(-q(k) D).
    rock_abundance: float = field(default=0.0, metadata=_help("k: total fraction of the area covered by rocks (0 = no rocks; Mars sites ~0.02-0.2)"))
    rock_min_diameter_m: float = field(default=0.3, metadata=_help("smallest rock diameter placed, metres"))
    rock_max_diameter_m: float = field(default=2.5, metadata=_help("largest rock diameter placed, metres"))
    rock_height_ratio: float = field(default=0.5, metadata=_help("mean rock height / diameter"))
    rock_embed_fraction: float = field(default=0.2, metadata=_help("share of each rock's height buried below the surface"))
    rock_sand_avoidance: float = field(default=0.8, metadata=_help("how strongly rocks avoid sand (0 = ignore sand, 1 = bedrock only)"))
    rock_max_count: int = field(default=20000, metadata=_help("refuse configurations expecting more rocks than this"))
    # Sand cover, dunes and ripples.
    sand_fraction: float = field(default=0.3, metadata=_help("fraction of the area covered by sand (low areas are preferred)"))
    sand_low_bias: float = field(default=0.6, metadata=_help("how much sand prefers low ground (0 = noise only, 1 = lows only)"))
    dune_amplitude_m: float = field(default=0.0, metadata=_help("crest-to-trough height of the dunes, metres (0 = none)"))
    dune_wavelength_m: float = field(default=15.0, metadata=_help("crest spacing of the dunes, metres"))
    dune_asymmetry: float = field(default=0.7, metadata=_help("where the crest sits in one period (0.5 = symmetric, toward 1 = steep lee face)"))
    dune_sinuosity: float = field(default=0.15, metadata=_help("crest waviness, in dune periods"))
    wind_azimuth_deg: float = field(default=30.0, metadata=_help("direction the wind blows toward (ccw from +x); lee faces point this way"))
    ripple_amplitude_m: float = field(default=0.0, metadata=_help("height of the smaller ripples on sand, metres (0 = none)"))
    ripple_wavelength_m: float = field(default=2.0, metadata=_help("ripple crest spacing, metres (needs >= 4 heightfield cells)"))

    def validate(self) -> None:
        _check_types(self, "terrain")
        s = "terrain."
        _require(33 <= self.resolution <= 8193, s + "resolution", "must be between 33 and 8193 samples", self.resolution)
        _require(self.extent_m > 0, s + "extent_m", "must be positive", self.extent_m)
        cell = self.extent_m / (self.resolution - 1)
        for name in ("relief_amplitude_m", "scarp_width_m", "layer_thickness_m", "dune_amplitude_m",
                     "ripple_amplitude_m", "rock_abundance", "crater_depth_ratio", "crater_rim_ratio",
                     "rock_embed_fraction"):
            _require(getattr(self, name) >= 0, s + name, "must not be negative", getattr(self, name))
        _require(self.relief_wavelength_m > 2 * cell, s + "relief_wavelength_m",
                 f"must be longer than two heightfield cells ({2 * cell:.3g} m)", self.relief_wavelength_m)
        _require(1 <= self.relief_octaves <= 16, s + "relief_octaves", "must be between 1 and 16", self.relief_octaves)
        for name in ("relief_roughness", "ridged_fraction", "layer_sharpness", "crater_degradation_min",
                     "crater_degradation_max", "sand_fraction", "sand_low_bias", "rock_sand_avoidance"):
            value = getattr(self, name)
            _require(0.0 <= value <= 1.0, s + name, "must be between 0 and 1", value)
        _require(-80.0 <= self.slope_deg <= 80.0, s + "slope_deg", "must be between -80 and 80 degrees", self.slope_deg)
        _require(self.scarp_width_m > 0 or self.scarp_height_m == 0, s + "scarp_width_m",
                 "must be positive when scarp_height_m is set", self.scarp_width_m)
        _require(self.crater_count >= 0, s + "crater_count", "must not be negative", self.crater_count)
        _require(self.crater_min_diameter_m > 0, s + "crater_min_diameter_m", "must be positive", self.crater_min_diameter_m)
        _require(self.crater_max_diameter_m > self.crater_min_diameter_m, s + "crater_max_diameter_m",
                 f"must exceed crater_min_diameter_m={self.crater_min_diameter_m}", self.crater_max_diameter_m)
        _require(self.crater_sfd_exponent > 0, s + "crater_sfd_exponent", "must be positive", self.crater_sfd_exponent)
        _require(self.crater_degradation_max >= self.crater_degradation_min, s + "crater_degradation_max",
                 f"must be >= crater_degradation_min={self.crater_degradation_min}", self.crater_degradation_max)
        _require(self.rock_abundance <= 0.5, s + "rock_abundance", "must be at most 0.5 (Mars sites span ~0.01-0.35)",
                 self.rock_abundance)
        _require(self.rock_min_diameter_m > 0, s + "rock_min_diameter_m", "must be positive", self.rock_min_diameter_m)
        _require(self.rock_max_diameter_m > self.rock_min_diameter_m, s + "rock_max_diameter_m",
                 f"must exceed rock_min_diameter_m={self.rock_min_diameter_m}", self.rock_max_diameter_m)
        _require(self.rock_height_ratio > 0, s + "rock_height_ratio", "must be positive", self.rock_height_ratio)
        _require(self.rock_embed_fraction < 1, s + "rock_embed_fraction", "must be below 1", self.rock_embed_fraction)
        _require(self.rock_max_count > 0, s + "rock_max_count", "must be positive", self.rock_max_count)
        if self.rock_abundance > 0:
            expected = expected_rock_count(self.rock_abundance, self.rock_min_diameter_m,
                                           self.rock_max_diameter_m, self.extent_m ** 2)
            _require(expected <= self.rock_max_count, s + "rock_min_diameter_m",
                     f"gives ~{expected:.0f} rocks, more than rock_max_count={self.rock_max_count}; "
                     "raise rock_min_diameter_m, lower rock_abundance or raise rock_max_count",
                     self.rock_min_diameter_m)
        _require(self.dune_wavelength_m >= 4 * cell, s + "dune_wavelength_m",
                 f"must span at least 4 heightfield cells ({4 * cell:.3g} m)", self.dune_wavelength_m)
        _require(0.5 <= self.dune_asymmetry < 1.0, s + "dune_asymmetry", "must be in [0.5, 1)", self.dune_asymmetry)
        _require(0.0 <= self.dune_sinuosity <= 1.0, s + "dune_sinuosity", "must be between 0 and 1", self.dune_sinuosity)
        if self.ripple_amplitude_m > 0:
            _require(self.ripple_wavelength_m >= 4 * cell, s + "ripple_wavelength_m",
                     f"must span at least 4 heightfield cells ({4 * cell:.3g} m) when ripples are on; "
                     "raise terrain.resolution or set ripple_amplitude_m = 0", self.ripple_wavelength_m)

    @property
    def cell_m(self) -> float:
        """Spacing between heightfield samples, metres."""
        return self.extent_m / (self.resolution - 1)


@dataclass
class RigConfig:
    """Where the cameras go. Heights in metres; see docs/terrain.md for each kind."""

    kind: str = field(default="rover_traverse", metadata=_help("camera layout", choices=RIG_KINDS))
    views: int = field(default=30, metadata=_help("number of camera views"))
    height_m: float = field(default=2.0, metadata=_help("rover/station: mast height above ground; orbit/aerial: altitude above the target"))
    radius_m: float = field(default=20.0, metadata=_help("orbit: circle radius; aerial: half-size of the surveyed square"))
    pitch_deg: float = field(default=-35.0, metadata=_help("camera elevation (negative looks down); orbit aims at the centre instead, nadir uses -90"))
    spacing_m: float = field(default=0.5, metadata=_help("rover: distance driven between consecutive views"))
    heading_deg: float = field(default=0.0, metadata=_help("rover: driving direction; panorama: first view; aerial: flight-line direction (azimuth)"))
    sweep_deg: float = field(default=360.0, metadata=_help("panorama/orbit: total azimuth covered"))
    wander_m: float = field(default=1.0, metadata=_help("rover: lateral amplitude of the gently curving path"))
    look_offset_deg: float = field(default=0.0, metadata=_help("rover: camera yaw relative to the driving direction (90 = looking left)"))
    yaw_sweep_deg: float = field(default=0.0, metadata=_help("rover: views alternate left/centre/right by this much (widens coverage)"))
    pivot_offset_m: float = field(default=0.0, metadata=_help("panorama: camera distance from the pan axis (0 = pure rotation, no parallax)"))
    pan_overlap: float = field(default=0.0, metadata=_help("panorama: least share of the horizontal field of view that neighbouring pointings overlap; too few views then cover less than sweep_deg (0 = always spread over sweep_deg)"))
    center_x_m: float = field(default=0.0, metadata=_help("site centre x (station, orbit target, aerial grid centre)"))
    center_y_m: float = field(default=0.0, metadata=_help("site centre y"))
    jitter_deg: float = field(default=0.0, metadata=_help("random yaw/pitch perturbation per view, degrees"))
    stereo_baseline_m: float = field(default=0.0, metadata=_help("> 0: views come in left/right pairs this far apart (MSL Navcam: 0.424 m)"))
    min_clearance_m: float = field(default=0.5, metadata=_help("cameras stay at least this high above the ground below them"))

    def validate(self) -> None:
        _check_types(self, "rig")
        s = "rig."
        _require(self.kind in RIG_KINDS, s + "kind", f"must be one of {', '.join(RIG_KINDS)}", self.kind)
        _require(1 <= self.views <= 10000, s + "views", "must be between 1 and 10000", self.views)
        _require(self.height_m > 0, s + "height_m", "must be positive", self.height_m)
        _require(self.radius_m > 0, s + "radius_m", "must be positive", self.radius_m)
        _require(-90.0 <= self.pitch_deg <= 90.0, s + "pitch_deg", "must be between -90 and 90", self.pitch_deg)
        _require(self.spacing_m > 0, s + "spacing_m", "must be positive", self.spacing_m)
        _require(0 < self.sweep_deg <= 360.0, s + "sweep_deg", "must be in (0, 360]", self.sweep_deg)
        for name in ("wander_m", "yaw_sweep_deg", "pivot_offset_m", "jitter_deg", "min_clearance_m", "stereo_baseline_m"):
            _require(getattr(self, name) >= 0, s + name, "must not be negative", getattr(self, name))
        _require(0.0 <= self.pan_overlap < 1.0, s + "pan_overlap", "must be in [0, 1)", self.pan_overlap)
        if self.stereo_baseline_m > 0:
            _require(self.views >= 2 and self.views % 2 == 0, s + "views",
                     "must be even (left/right pairs) when rig.stereo_baseline_m is set", self.views)
        if self.kind == "aerial_oblique":
            _require(-85.0 <= self.pitch_deg <= -10.0, s + "pitch_deg",
                     "must be between -85 and -10 for aerial_oblique (use aerial_nadir to look straight down)",
                     self.pitch_deg)


@dataclass
class RenderConfig:
    """The render camera and Cycles settings. ``fov_deg`` is the horizontal field of view."""

    width: int = field(default=960, metadata=_help("image width, pixels"))
    height: int = field(default=540, metadata=_help("image height, pixels"))
    samples: int = field(default=32, metadata=_help("Cycles samples per pixel"))
    camera: str = field(default="generic_rgb", metadata=_help("camera preset the other values came from", choices=tuple(CAMERA_PRESETS)))
    grayscale: bool = field(default=False, metadata=_help("write one-channel (panchromatic) images, like Navcam"))
    fov_deg: float = field(default=60.0, metadata=_help("horizontal field of view, degrees"))
    sensor_width_mm: float = field(default=36.0, metadata=_help("sensor width used to express the focal length in mm"))
    near_m: float = field(default=0.05, metadata=_help("camera clip start, metres"))
    far_m: float = field(default=2000.0, metadata=_help("camera clip end, metres"))

    def validate(self) -> None:
        _check_types(self, "render")
        s = "render."
        _require(8 <= self.width <= 16384, s + "width", "must be between 8 and 16384 pixels", self.width)
        _require(8 <= self.height <= 16384, s + "height", "must be between 8 and 16384 pixels", self.height)
        _require(1 <= self.samples <= 65536, s + "samples", "must be between 1 and 65536", self.samples)
        _require(self.camera in CAMERA_PRESETS, s + "camera", f"must be one of {', '.join(CAMERA_PRESETS)}", self.camera)
        _require(1.0 <= self.fov_deg <= 170.0, s + "fov_deg", "must be between 1 and 170 degrees", self.fov_deg)
        _require(self.sensor_width_mm > 0, s + "sensor_width_mm", "must be positive", self.sensor_width_mm)
        _require(self.near_m > 0, s + "near_m", "must be positive", self.near_m)
        _require(self.far_m > self.near_m, s + "far_m", f"must exceed near_m={self.near_m}", self.far_m)

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (square pixels): ``fx = fy``."""
        return 0.5 * self.width / math.tan(math.radians(self.fov_deg) / 2)

    @property
    def focal_mm(self) -> float:
        """Focal length in millimetres for a sensor ``sensor_width_mm`` wide (horizontal fit)."""
        return 0.5 * self.sensor_width_mm / math.tan(math.radians(self.fov_deg) / 2)

    @property
    def vertical_fov_deg(self) -> float:
        return math.degrees(2 * math.atan(math.tan(math.radians(self.fov_deg) / 2) * self.height / self.width))


def camera_preset(name: str, **overrides: Any) -> RenderConfig:
    """A :class:`RenderConfig` with the named camera preset's values (then ``overrides``)."""
    if name not in CAMERA_PRESETS:
        raise ConfigError(f"render.camera: unknown camera preset {name!r}",
                          hint=f"known: {', '.join(CAMERA_PRESETS)}")
    values = {**CAMERA_PRESETS[name], "camera": name, **overrides}
    config = RenderConfig(**values)
    config.validate()
    return config
