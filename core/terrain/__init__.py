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

from ..config import config_to_dict
from .config import CAMERA_PRESETS, RIG_KINDS, RenderConfig, RigConfig, TerrainConfig, camera_preset
from .scene_config import SceneConfig
from .heightfield import Terrain, generate_terrain, load_terrain, save_terrain
from .mesh import heightfield_mesh, rock_mesh, rocks_mesh, terrain_mesh
from .presets import list_presets, load_preset, load_scene_config, save_scene_config, scene_config_from_dict
from .rigs import CameraPose, ground_depth, intrinsics, make_camera_rig, views_beyond_terrain

__all__ = [
    "CAMERA_PRESETS", "RIG_KINDS", "CameraPose", "RenderConfig", "RigConfig", "SceneConfig", "Terrain",
    "TerrainConfig", "camera_preset", "config_to_dict", "generate_terrain", "ground_depth", "heightfield_mesh", "intrinsics",
    "list_presets", "load_terrain", "rock_mesh", "rocks_mesh", "save_terrain", "terrain_mesh",
    "load_preset", "load_scene_config", "make_camera_rig", "save_scene_config", "scene_config_from_dict",
    "views_beyond_terrain",
]
