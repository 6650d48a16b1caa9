"""Headless entry point: generate, render and export one synthetic Mars scene.

Run with a Python that has the ``bpy`` module::

    python -m esgs.esgs_addon.make_scene --preset cratered_plain --seed 3 --views 30 \\
        --resolution 480x270 --out scenes/plain_s3

(``examples/make_mars_scene.py`` wraps it for ``blender -b --python``.) Blocking; progress
goes to the console. ``esgs scene`` runs :func:`make_scene` as the ``"scene"`` job of the
child-process runtime (:func:`child_job`, see :mod:`esgs.core.runtime`).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from ..core.commands.scene import add_arguments, job_from_args
from ..core.errors import ESGSError
from ..core.progress import ConsoleProgress, JsonLinesProgress, combine


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="make_scene", description=__doc__.splitlines()[0])
    add_arguments(parser)
    parser.add_argument("--save-blend", type=Path, default=None, help="also save the generated scene as this .blend file")
    return parser


def make_scene(job, out: Path, *, progress=None, save_blend: Path | None = None) -> Path:
    """Build the scene of ``job`` (a SceneJob) in a fresh Blender file and export it to ``out``."""
    import bpy

    from .render_dataset import render_dataset

    config = job.scene_config()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if job.mesh:
        from .mesh_scene import build_mesh_scene

        objects = build_mesh_scene(config, progress=progress)
    else:
        from .terrain_scene import build_terrain_scene

        objects = build_terrain_scene(config, progress=progress)
    result = render_dataset(objects, out, progress=progress, sfm=job.sfm, overwrite=job.overwrite,
                            points_per_view=job.points_per_view)
    if save_blend is not None:
        bpy.ops.wm.save_as_mainfile(filepath=str(Path(save_blend).resolve()))
    return result


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: sys.argv[1:]) and make the scene; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.list_presets:
        from ..core.terrain import list_presets

        print("\n".join(list_presets()))
        return 0
    console = ConsoleProgress()
    events = JsonLinesProgress(args.events) if args.events else None
    progress = combine(console, events)
    try:
        if args.out is None:
            parser.error("--out is required")
        job = job_from_args(args)
        out = make_scene(job, args.out, progress=progress, save_blend=args.save_blend)
    except ESGSError as error:
        print(f"make_scene: error: {error}", file=sys.stderr)
        return 2
    finally:
        console.close()
        if events is not None:
            events.close()
    print(f"make_scene: wrote {out}", file=sys.stderr)
    return 0


def child_job(data: dict, context) -> dict:
    """The ``"scene"`` job of the child-process runtime: ``data`` is ``{"job": SceneJob as a
    dict, "out": folder}`` (see :func:`esgs.core.terrain.scene_job.render_scene`); returns ``{"out": folder}``."""
    from ..core.terrain.scene_job import SceneJob
    from ..core.config import config_from_dict

    job = config_from_dict(SceneJob, data["job"], source=context.config_path)
    out = make_scene(job, Path(data["out"]), progress=context.progress)
    return {"out": str(out)}


if __name__ == "__main__":
    sys.exit(main())
