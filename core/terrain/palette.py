"""How a synthetic scene looks: its sky's colours and how saturated its ground is.

The generator had one look: a butterscotch sky gradient over reddish-brown ground. A network
that learns to mark the sky from such scenes learns that pairing: the NDN completion network
marked the generator's sky (IoU 0.96-0.98) but none of the real mesh's rover views (grey ground
under an orange sky) nor of real Navcam frames (grey, sky brighter than the ground).
``"varied"`` draws each scene's palette from its seed: sky hues from the dusty butterscotch to
neutral grey (a quarter fully grey), brightness, how the horizon haze fades towards the zenith,
the haze's height, and, independently, the ground's saturation (grey ground in about a third of
the scenes). ``"mars"`` is the fixed look (every preset's default: the scenes users render and
the studies' scenes are unchanged). The world also lights the scene, so a grey sky greys the
shadows a little too (about one 8-bit level on the terrain of a ``rover_horizon`` scene).

The palette is plain data so that ``core`` owns it; ``esgs_addon.mars_material`` turns it into
shader nodes (``make_sky_world``, and the materials' saturation).
"""
from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np

#: the palettes a scene config may name
PALETTES = ("mars", "varied")

Colour = tuple[float, float, float]


@dataclass(frozen=True)
class ScenePalette:
    """A scene's look. Colours: linear RGB in [0, 1] of the sky gradient's stops along the view
    direction's elevation.

    ``distant_ground``: just below the horizon (a plain past the terrain's edge); ``nadir``:
    straight down (darker); ``horizon``: the bright haze at the horizon; ``haze``: where the haze fades,
    at ``haze_height`` (the gradient's position, 0.5 = horizon, 1 = zenith); ``zenith``: straight
    up. ``strength``: the world's emission scale before the sun-elevation factor (the varied looks
    keep 1 and scale their colours instead).
    ``surface_saturation``: the terrain's and rocks' albedo saturation (0 grey, 1 as designed).
    """

    nadir: Colour
    distant_ground: Colour
    horizon: Colour
    haze: Colour
    zenith: Colour
    haze_height: float = 0.62
    strength: float = 1.0
    surface_saturation: float = 1.0

    def validate(self) -> None:
        from ..errors import ConfigError

        for name in ("nadir", "distant_ground", "horizon", "haze", "zenith"):
            colour = getattr(self, name)
            if len(colour) != 3 or not all(0.0 <= float(c) <= 1.0 for c in colour):
                raise ConfigError(f"palette colour {name} must be three values in [0, 1], got {colour}")
        if not 0.505 < self.haze_height < 1.0:
            raise ConfigError(f"palette haze_height must be in (0.505, 1), got {self.haze_height}")
        if not 0.0 <= self.surface_saturation <= 2.0:
            raise ConfigError(f"palette surface_saturation must be in [0, 2], got {self.surface_saturation}")
        if self.strength <= 0:
            raise ConfigError(f"palette strength must be positive, got {self.strength}")


#: the generator's original look: butterscotch horizon, darker brown zenith, the ground as designed
MARS_PALETTE = ScenePalette(nadir=(0.16, 0.08, 0.04), distant_ground=(0.30, 0.16, 0.08), horizon=(0.72, 0.50, 0.32),
                            haze=(0.45, 0.28, 0.16), zenith=(0.20, 0.12, 0.07))


def _toward_grey(colour: Colour, saturation: float, brightness: float) -> Colour:
    """``colour`` with its HSV saturation scaled by ``saturation`` and its value by ``brightness``."""
    hue, sat, value = colorsys.rgb_to_hsv(*colour)
    red, green, blue = colorsys.hsv_to_rgb(hue, sat * saturation, min(1.0, value * brightness))
    return (red, green, blue)


def varied_palette(seed: int) -> ScenePalette:
    """A palette drawn from ``seed`` (the scene's): the same seed gives the same look.

    Saturation 0 (grey) with probability 1/4, else uniform in [0.15, 1.2] of the Mars sky's;
    brightness 0.6-1.6x; the zenith 0.25-1.3x the horizon's brightness (darker, flat, or brighter
    as towards the sun); the haze stop at 0.53-0.80; the ground band's colour follows the sky's
    saturation so a grey sky does not sit over a butterscotch plain. The ground's albedo
    saturation is drawn independently: 0 (grey) with probability 1/3, else 0.3-1.2.
    """
    generator = np.random.default_rng([int(seed), 0x5C7])
    saturation = 0.0 if generator.random() < 0.25 else float(generator.uniform(0.15, 1.2))
    brightness = float(generator.uniform(0.6, 1.6))
    zenith_ratio = float(generator.uniform(0.25, 1.3))
    horizon = _toward_grey(MARS_PALETTE.horizon, saturation, brightness)
    zenith = _toward_grey(MARS_PALETTE.horizon, saturation, brightness * zenith_ratio)
    haze = tuple(0.5 * (h + z) for h, z in zip(horizon, zenith))
    ground = _toward_grey(MARS_PALETTE.distant_ground, saturation, float(generator.uniform(0.7, 1.3)))
    nadir = tuple(0.53 * g for g in ground)  # the Mars sky's ratio of the two ground stops
    haze_height = float(generator.uniform(0.53, 0.80))
    surface = 0.0 if generator.random() < 1 / 3 else float(generator.uniform(0.3, 1.2))
    return ScenePalette(nadir=nadir, distant_ground=ground, horizon=horizon, haze=haze, zenith=zenith,  # type: ignore[arg-type]
                        haze_height=haze_height, surface_saturation=surface)


def scene_palette(name: str, seed: int) -> ScenePalette:
    """The palette a scene config names (``"mars"`` or ``"varied"``, drawn from ``seed``)."""
    from ..errors import ConfigError

    if name == "mars":
        return MARS_PALETTE
    if name == "varied":
        return varied_palette(seed)
    raise ConfigError(f"unknown palette {name!r}", hint=f"use one of {', '.join(PALETTES)}")
