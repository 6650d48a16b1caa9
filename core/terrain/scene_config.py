"""SceneConfig: one synthetic scene (terrain, rig, render camera, light) and its checks.

Apart from :mod:`.config` (the parts' settings) because its check that no view sees past
the terrain needs the camera rigs, and the rigs need the parts' settings.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..errors import ConfigError
from .config import RenderConfig, RigConfig, TerrainConfig, _check_types, _help, _require
from .rigs import horizon_problem
from .palette import PALETTES


@dataclass
class SceneConfig:
    """Everything that defines one synthetic scene; with ``seed`` it reproduces it exactly."""

    name: str = field(default="custom", metadata=_help("scene (preset) name"))
    seed: int = field(default=0, metadata=_help("random seed (non-negative); same seed + config = same scene"))
    description: str = field(default="", metadata=_help("what the scene is meant to show"))
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    rig: RigConfig = field(default_factory=RigConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    sun_elevation_deg: float = field(default=35.0, metadata=_help("sun height above the horizon, degrees"))
    sun_azimuth_deg: float = field(default=135.0, metadata=_help("direction toward the sun (ccw from +x), degrees"))
    sky: bool = field(default=False, metadata=_help("the views show the horizon and sky (else every pixel sees terrain)"))
    palette: str = field(default="mars", metadata=_help(
        "the scene's look: mars (the fixed butterscotch sky over reddish ground) or varied (drawn from the "
        "seed: sky butterscotch to grey, brightness, haze; ground saturation; training data for sky detection)"))

    def validate(self) -> None:
        _check_types(self, "")
        _require(self.seed >= 0, "seed", "must be a non-negative integer", self.seed)
        _require(0.0 < self.sun_elevation_deg <= 90.0, "sun_elevation_deg", "must be in (0, 90]", self.sun_elevation_deg)
        _require(self.palette in PALETTES, "palette", f"must be one of {', '.join(PALETTES)}",
                 self.palette)
        self.terrain.validate()
        self.rig.validate()
        self.render.validate()
        if not self.sky:
            problem = horizon_problem(self.rig, self.render, self.terrain, seed=self.seed)
            if problem:
                raise ConfigError(f"sky is false but {problem}",
                                  hint="set sky = true, or look further down (rig.pitch_deg; for an orbit raise "
                                       "rig.height_m), or shrink rig.radius_m / rig.spacing_m, or enlarge "
                                       "terrain.extent_m")

    def sun_direction(self) -> tuple[float, float, float]:
        """Unit vector from the ground toward the sun, world frame ``[3]``."""
        elevation = math.radians(self.sun_elevation_deg)
        azimuth = math.radians(self.sun_azimuth_deg)
        return (math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation))
