"""Synthetic Mars terrain (numpy only): heightfield, craters, rocks, dunes, camera rigs, presets.

Typical use::

    cfg = load_preset("cratered_plain", seed=7, views=30, resolution=(480, 270))
    terrain = generate_terrain(cfg.terrain, seed=cfg.seed)
    cameras = make_camera_rig(cfg.rig, cfg.render, terrain, seed=cfg.seed)
    json_ready = config_to_dict(cfg)

Conventions (frames, grid layout, units) are in :mod:`.heightfield`, :mod:`.rigs` and
docs/terrain.md.
"""
from __future__ import annotations

from typing import Any

# names -> the submodule that defines them, imported on first use: `esgs scene --help` and
# the add-on's settings read SceneJob (terrain.scene_job) without loading scipy and numpy
_LAZY = {
    "config_to_dict": "..config",
    **dict.fromkeys(("CAMERA_PRESETS", "RIG_KINDS", "RenderConfig", "RigConfig", "TerrainConfig", "camera_preset"),
                    ".config"),
    "SceneConfig": ".scene_config",
    **dict.fromkeys(("Terrain", "generate_terrain", "load_terrain", "save_terrain"), ".heightfield"),
    **dict.fromkeys(("heightfield_mesh", "rock_mesh", "rocks_mesh", "terrain_mesh"), ".mesh"),
    **dict.fromkeys(("list_presets", "load_preset", "load_scene_config", "save_scene_config",
                     "scene_config_from_dict"), ".presets"),
    **dict.fromkeys(("CameraPose", "ground_depth", "intrinsics", "make_camera_rig", "views_beyond_terrain"), ".rigs"),
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(name)
    import importlib

    return getattr(importlib.import_module(module, __name__), name)
