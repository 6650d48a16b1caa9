"""A request to render a synthetic (or mesh) scene folder, and the one way to run it.

:class:`SceneJob` says what to generate and where; :func:`render_scene` checks it and runs
the ``"scene"`` job of the child-process runtime (Blender's ``bpy`` never enters ``core``).
``esgs scene``, the demo, the bench and the NDN data builder all go through it.
"""
from __future__ import annotations

import argparse
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .palette import PALETTES

#: ``SceneJob.palette`` value that keeps the preset's or config file's look. A named choice, not
#: "", because the add-on turns the choices into a drop-down, whose items need identifiers.
KEEP_PALETTE = "preset"


@dataclass
class SceneJob:
    """What to generate and where. Zero for views/width/height/samples keeps the preset's value."""

    preset: str = field(default="cratered_plain", metadata={"help": "scene preset (see --list-presets)"})
    config: str = field(default="", metadata={"help": "scene config file (.toml preset format or saved .json) instead of a preset"})
    seed: int = field(default=-1, metadata={"help": "random seed; the same seed and settings give the same scene (-1 = the preset's or file's)"})
    views: int = field(default=0, metadata={"help": "number of camera views (0 = the preset's)"})
    width: int = field(default=0, metadata={"help": "image width in pixels (0 = the preset's)"})
    height: int = field(default=0, metadata={"help": "image height in pixels (0 = the preset's)"})
    samples: int = field(default=0, metadata={"help": "Cycles samples per pixel (0 = the preset's)"})
    points_per_view: int = field(default=2000, metadata={"help": "surface pixels per view lifted to COLMAP points3D"})
    sfm: bool = field(default=False, metadata={"help": "also run pycolmap SfM on the renders into sparse_sfm/0"})
    overwrite: bool = field(default=False, metadata={"help": "replace an existing output folder (only once the new one is complete)"})
    mesh: str = field(default="", metadata={"help": "render this textured mesh (.glb/.gltf/.obj/.ply) instead of a synthetic preset (docs/mesh_scenes.md)"})
    rig: str = field(default="traverse", metadata={
        "help": "with --mesh: camera layout (mixed = aerial orbit + rover views with sky)",
        "choices": ("traverse", "orbit", "mixed")})
    mast_height_m: float = field(default=2.0, metadata={"help": "with --mesh --rig traverse: camera height above the surface, metres"})
    pitch_deg: float = field(default=-30.0, metadata={
        "help": "with --mesh --rig traverse: camera pitch in degrees (negative looks down; near 0 the views "
                "show the horizon and the sky)"})
    rover_views: int = field(default=0, metadata={
        "help": "with --mesh --rig mixed: how many of the views are rover-height views (0 = 40 percent)"})
    rover_pitch_deg: float = field(default=2.0, metadata={
        "help": "with --mesh --rig mixed: rover views' pitch in degrees (the horizon and sky in frame)"})
    site_center: str = field(default="", metadata={
        "help": "with --mesh --rig orbit or mixed: the site's centre as X,Y in the mesh's metres (Blender's "
                "frame, +Z up), e.g. 60,-40; empty = the middle of the mesh's footprint"})
    palette: str = field(default=KEEP_PALETTE, metadata={
        "help": "a synthetic scene's look (sky colours, ground saturation): mars (fixed), varied (drawn from "
                "the seed) or preset (the preset's or file's)", "choices": (KEEP_PALETTE, *PALETTES)})

    def validate(self) -> None:
        from ..errors import ConfigError

        for name in ("views", "width", "height", "samples"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must not be negative (0 keeps the preset's), got {getattr(self, name)}")
        if self.seed < -1:
            raise ConfigError(f"seed must be a non-negative integer (or -1 for the preset's), got {self.seed}")
        if (self.width == 0) != (self.height == 0):
            raise ConfigError(f"set both width and height (or neither), got {self.width}x{self.height}")
        if self.points_per_view < 1:
            raise ConfigError(f"points_per_view must be positive, got {self.points_per_view}")
        if self.mesh and self.config:
            raise ConfigError("--mesh and --config exclude each other", hint="a mesh scene takes its settings from the flags")
        if self.palette not in (KEEP_PALETTE, *PALETTES):
            raise ConfigError(f"palette must be one of {KEEP_PALETTE}, {', '.join(PALETTES)}, got {self.palette!r}")
        if self.site_center:
            self.site_center_xy()
            if not self.mesh or self.rig == "traverse":
                raise ConfigError("--site-center applies to --mesh scenes with --rig orbit or mixed",
                                  hint="a traverse drives from random places over the whole mesh; drop --site-center")
        if self.mesh and self.palette != KEEP_PALETTE:
            raise ConfigError("--palette applies to synthetic scenes only",
                              hint="a --mesh scene keeps its mesh's texture and the fixed Mars sky; drop --palette")

    def site_center_xy(self) -> tuple[float, float] | None:
        """``site_center`` as (x, y) metres, or None for the middle of the footprint."""
        from ..errors import ConfigError

        if not self.site_center:
            return None
        parts = self.site_center.split(",")
        try:
            if len(parts) != 2:
                raise ValueError
            x, y = (float(part) for part in parts)
        except ValueError:
            raise ConfigError(f"site_center must be two numbers X,Y in metres, got {self.site_center!r}",
                              hint="for example --site-center 60,-40") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ConfigError(f"site_center must be finite, got {self.site_center!r}")
        return x, y

    def mesh_scene_config(self) -> Any:
        """The validated MeshSceneConfig of a ``--mesh`` job (DatasetError for a missing mesh file)."""
        import dataclasses
        from pathlib import Path

        from .mesh_scene import MeshRigConfig, MeshSceneConfig  # moved into terrain by the layout change

        base = MeshSceneConfig()
        render = dataclasses.replace(base.render)
        if self.width:
            render.width, render.height = self.width, self.height
        if self.samples:
            render.samples = self.samples
        rig = MeshRigConfig(kind=self.rig, views=self.views or base.rig.views, mast_height_m=self.mast_height_m,
                            pitch_deg=self.pitch_deg, rover_views=self.rover_views,
                            rover_pitch_deg=self.rover_pitch_deg)
        centre = self.site_center_xy()
        if centre is not None:
            rig.center_x_m, rig.center_y_m = centre
        config = MeshSceneConfig(mesh=str(Path(self.mesh).expanduser().resolve()), name=Path(self.mesh).stem,
                                 seed=self.seed if self.seed >= 0 else 0, rig=rig, render=render)
        config.validate()
        return config

    def scene_config(self) -> Any:
        """The validated SceneConfig this job renders (raises ConfigError for bad settings)."""
        from ..config import config_to_dict
        from .presets import load_preset, load_scene_config, scene_config_from_dict

        self.validate()
        if self.mesh:
            return self.mesh_scene_config()
        if not self.config:
            config = load_preset(self.preset, seed=self.seed if self.seed >= 0 else None, views=self.views or None,
                                 resolution=(self.width, self.height) if self.width else None,
                                 samples=self.samples or None)
            if self.palette == KEEP_PALETTE:
                return config
            data = config_to_dict(config)
            data["palette"] = self.palette
            return scene_config_from_dict(data, source=f"preset {self.preset}")
        data = config_to_dict(load_scene_config(self.config))
        if self.palette != KEEP_PALETTE:
            data["palette"] = self.palette
        if self.seed >= 0:
            data["seed"] = self.seed
        if self.views:
            data["rig"]["views"] = self.views
        if self.width:
            data["render"]["width"], data["render"]["height"] = self.width, self.height
        if self.samples:
            data["render"]["samples"] = self.samples
        return scene_config_from_dict(data, source=self.config)


def parse_resolution(text: str) -> tuple[int, int]:
    """``"480x270"`` -> (480, 270)."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match:
        raise argparse.ArgumentTypeError(f"resolution must look like 480x270, got {text!r}")
    return int(match.group(1)), int(match.group(2))


def render_scene(job: SceneJob, out: str | Path, progress: Any = None, *, verbose: bool = False) -> Path:
    """Generate, render and export the scene of ``job`` into ``out`` in a Blender child process.

    Bad settings, an existing ``out`` (without ``job.overwrite``) and a Python without the
    bpy module fail here, before Blender starts. Returns ``out``.

    Raises:
        ConfigError, DatasetError: here or from the child (the same type).
    """
    from ..progress import no_progress
    from ..runtime import run_job

    out = Path(out)
    check_request(job, out)
    run_job("scene", {"job": job, "out": str(out)}, progress or no_progress, task="scene generation",
            verbose=verbose)
    return out


def check_request(job: SceneJob, out: Path) -> Any:
    """Fail before Blender starts: bad settings, an existing ``out`` (without overwrite), no
    bpy module. Returns the job's validated scene config."""
    import importlib.util

    from ..errors import ConfigError

    config = job.scene_config()
    if out.exists() and not job.overwrite:
        raise ConfigError("output folder already exists", path=out, hint="choose another folder or pass --overwrite")
    if importlib.util.find_spec("bpy") is None:
        raise ConfigError("rendering needs Blender's bpy module, which this Python does not have",
                          hint="pip install bpy==5.0.1, or run: blender -b --python examples/make_mars_scene.py -- "
                               "--preset ... --out DIR")
    return config
