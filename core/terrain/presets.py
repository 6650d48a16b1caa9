"""Named scene presets (TOML files in ``presets/``) and scene-config files.

A preset file holds top-level scene values (``name``, ``description``, ``seed``,
``sun_elevation_deg``, ``sun_azimuth_deg``, ``sky``) and the tables ``[terrain]``,
``[rig]`` and ``[render]``; anything left out keeps the dataclass default. In ``[render]``,
``camera = "navcam"`` first fills width, height, field of view and grayscale from that
camera preset; other keys in the table then override those. Saved scene configs are JSON
(every field explicit), readable by :func:`load_scene_config`.
"""
from __future__ import annotations

import copy
import json
import tomllib
from pathlib import Path
from typing import Any

from ..config import config_from_dict, config_to_dict
from ..errors import ConfigError
from ..io_utils import atomic_write_json
from .config import CAMERA_PRESETS
from .scene_config import SceneConfig

PRESET_DIR = Path(__file__).resolve().parent / "presets"


def list_presets() -> list[str]:
    """Names of the bundled presets, sorted."""
    return sorted(path.stem for path in PRESET_DIR.glob("*.toml"))


def preset_path(name: str) -> Path:
    """The TOML file of preset ``name``; ConfigError when there is none."""
    if not isinstance(name, str) or not name or "/" in name or "\\" in name or name.startswith("."):
        raise ConfigError(f"preset name must be a plain name, got {name!r}", hint=f"available: {', '.join(list_presets())}")
    path = PRESET_DIR / f"{name}.toml"
    if not path.is_file():
        raise ConfigError(f"unknown scene preset {name!r}", hint=f"available: {', '.join(list_presets())}")
    return path


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError as err:
        raise ConfigError("scene config file not found", path=path) from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"not valid TOML: {err}", path=path) from err


def scene_config_from_dict(data: dict[str, Any], *, source: str | Path | None = None) -> SceneConfig:
    """A validated :class:`SceneConfig` from a preset-style dict (render camera preset expanded)."""
    if not isinstance(data, dict):
        raise ConfigError("a scene config must be a table / JSON object", path=source)
    data = copy.deepcopy(data)
    render = data.get("render", {})
    if not isinstance(render, dict):
        raise ConfigError("render must be a table", path=source)
    camera = render.get("camera", "generic_rgb")
    if camera not in CAMERA_PRESETS:
        raise ConfigError(f"render.camera: unknown camera preset {camera!r}", path=source,
                          hint=f"known: {', '.join(CAMERA_PRESETS)}")
    data["render"] = {**CAMERA_PRESETS[camera], "camera": camera, **render}
    for table in ("terrain", "rig"):
        if table in data and not isinstance(data[table], dict):
            raise ConfigError(f"{table} must be a table", path=source)
    return config_from_dict(SceneConfig, data, source=source)


def load_preset(name: str, *, seed: int | None = None, views: int | None = None,
                resolution: tuple[int, int] | None = None, samples: int | None = None,
                camera: str | None = None) -> SceneConfig:
    """The validated scene config of preset ``name``, with optional overrides.

    camera: a camera preset that replaces the preset's render camera (width, height,
    field of view, grayscale); resolution: (width, height) in pixels, applied after it.
    Raises ConfigError for an unknown preset or an invalid result, before any heavy work.
    """
    path = preset_path(name)
    data = _read_toml(path)
    data.setdefault("name", name)
    if seed is not None:
        data["seed"] = seed
    if views is not None:
        data.setdefault("rig", {})["views"] = views
    render = data.setdefault("render", {})
    if camera is not None:
        render = {key: value for key, value in render.items() if key not in ("width", "height", "fov_deg", "grayscale")}
        render["camera"] = camera
    if resolution is not None:
        try:
            width, height = resolution
        except (TypeError, ValueError) as err:
            raise ConfigError(f"resolution must be (width, height), got {resolution!r}") from err
        render["width"], render["height"] = width, height
    if samples is not None:
        render["samples"] = samples
    data["render"] = render
    return scene_config_from_dict(data, source=path)


def load_scene_config(path: str | Path) -> SceneConfig:
    """Read a scene config from a ``.toml`` (preset format) or ``.json`` (saved) file."""
    path = Path(path)
    if path.suffix.lower() == ".toml":
        return scene_config_from_dict(_read_toml(path), source=path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise ConfigError("scene config file not found", path=path) from err
    except json.JSONDecodeError as err:
        raise ConfigError(f"not valid JSON: {err}", path=path) from err
    return scene_config_from_dict(data, source=path)


def save_scene_config(config: SceneConfig, path: str | Path) -> None:
    """Write the full scene config (every field, seed included) as JSON, atomically."""
    atomic_write_json(path, config_to_dict(config))
