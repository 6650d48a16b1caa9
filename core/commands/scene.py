"""``esgs scene``: generate, render and export a synthetic Mars scene folder.

Rendering needs Blender (the ``bpy`` module or a Blender binary), which ``core`` never
imports. This command checks the request here (bad settings fail at once, before any
work), then runs the ``"scene"`` job of the child-process runtime (:mod:`esgs.core.runtime`,
the add-on's ``make_scene``) with the SceneJob as its config file and relays its progress
events to the console. The child's own output (Blender's log) is shown only with ``--verbose``.
:func:`esgs.core.terrain.scene_job.render_scene` is the same for scripts (the demo, the bench,
the NDN data builder).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..terrain.scene_job import SceneJob, check_request, parse_resolution, render_scene  # noqa: F401 - the command's API

HELP = "generate a synthetic Mars scene (terrain, rocks, cameras), render it with Cycles and export a scene folder"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..config import add_dataclass_arguments

    add_dataclass_arguments(parser, SceneJob, skip=("width", "height"))
    parser.add_argument("--resolution", type=parse_resolution, default=None, metavar="WxH",
                        help="image size in pixels, e.g. 480x270 (default: the preset's)")
    parser.add_argument("--out", type=Path, default=None, help="scene folder to create (required unless --list-presets)")
    parser.add_argument("--list-presets", action="store_true", help="print the preset names and exit")
    parser.add_argument("--events", type=Path, default=None, help="also append progress events to this JSON-lines file")
    parser.add_argument("--verbose", action="store_true", help="show Blender's own log")


def job_from_args(args: argparse.Namespace) -> SceneJob:
    """The SceneJob of parsed arguments (``--resolution`` fills width and height)."""
    from ..config import dataclass_from_args

    job = dataclass_from_args(SceneJob, args)
    if getattr(args, "resolution", None):
        job.width, job.height = args.resolution
    job.validate()
    return job


def run(args: argparse.Namespace) -> int:
    import sys

    from ..errors import ConfigError
    from ..progress import ConsoleProgress, JsonLinesProgress, combine

    if args.list_presets:
        from ..terrain import list_presets, load_preset

        for name in list_presets():
            print(f"{name:<22} {load_preset(name).description}")
        return 0
    if args.out is None:
        raise ConfigError("--out is required", hint="e.g. esgs scene --preset cratered_plain --out scenes/plain")
    job = job_from_args(args)
    out = Path(args.out)
    config = check_request(job, out)
    console = ConsoleProgress()
    events = JsonLinesProgress(args.events) if args.events else None
    progress = combine(console, events)
    print(f"esgs scene: {config.name}, seed {config.seed}, {config.rig.views} views at "
          f"{config.render.width}x{config.render.height}, {config.render.samples} samples -> {out}", file=sys.stderr)
    try:
        render_scene(job, out, progress, verbose=args.verbose)
    finally:
        console.close()
        if events is not None:
            events.close()
    print(f"esgs scene: wrote {out}", file=sys.stderr)
    return 0
