"""``esgs labels``: depth/normal label maps of a COLMAP scene rendered from a mesh (priors/labels/).

    esgs labels SCENE --mesh MESH            # a mesh you have (same frame and units as the cameras)
    esgs labels SCENE --reconstruct          # a mesh rebuilt on the CPU from the scene's images
    esgs labels SCENE --reconstruct --report # synthetic scenes: AbsRel / delta1 against priors/gt

See docs/labels.md.
"""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "render depth/normal labels (priors/labels/) of a scene from a mesh, given or reconstructed from the images"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..config import add_dataclass_arguments
    from ..labels.fill import FillOptions
    from ..labels.reconstruct import ReconstructOptions
    from ..labels.stereo import StereoOptions

    parser.add_argument("scene", type=Path, help="scene folder (images/ + sparse/0)")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--mesh", type=Path, default=None, help="mesh file (.ply/.obj/...) in the cameras' frame and units")
    source.add_argument("--reconstruct", action="store_true",
                        help="rebuild a mesh from the scene's images and poses first (SCENE/mesh/reconstructed.ply)")
    parser.add_argument("--report", action="store_true",
                        help="synthetic scenes: compare the labels with priors/gt (AbsRel, delta1), print a table "
                             "and write priors/labels/accuracy.json")
    parser.add_argument("--samples", type=int, default=0,
                        help="Cycles samples per pixel (0 = 1: depth is the first sample's)")
    parser.add_argument("--flat", action="store_true", help="shade the mesh flat (default: smooth vertex normals)")
    add_dataclass_arguments(parser, FillOptions)
    add_dataclass_arguments(parser, ReconstructOptions, skip=("stereo",))
    add_dataclass_arguments(parser, StereoOptions, prefix="stereo_")
    parser.add_argument("--events", type=Path, default=None, help="also append progress events to this JSON-lines file")
    parser.add_argument("--verbose", action="store_true", help="show Blender's own log")


def run(args: argparse.Namespace) -> int:
    import sys

    from ..config import dataclass_from_args
    from ..labels.accuracy import format_accuracy_table
    from ..labels.fill import FillOptions
    from ..labels.pipeline import LabelJob, run_label_job
    from ..labels.reconstruct import ReconstructOptions
    from ..labels.stereo import StereoOptions
    from ..progress import ConsoleProgress, JsonLinesProgress, combine
    from ..formats.scene_dir import PriorSource, SceneDir

    reconstruct_options = dataclass_from_args(ReconstructOptions, args)
    reconstruct_options.stereo = dataclass_from_args(StereoOptions, args, prefix="stereo_")
    job = LabelJob(scene=args.scene, mesh=args.mesh, reconstruct=args.reconstruct,
                   reconstruct_options=reconstruct_options, fill=dataclass_from_args(FillOptions, args),
                   samples=args.samples, smooth=not args.flat, report=args.report)
    console = ConsoleProgress()
    events = JsonLinesProgress(args.events) if args.events else None
    try:
        result = run_label_job(job, combine(console, events), verbose=args.verbose)
    finally:
        console.close()
        if events is not None:
            events.close()
    views = result["labels"]["views"]
    filled = sum(view["filled_fraction"] for view in views) / len(views)
    empty = sum(view["empty_fraction"] for view in views) / len(views)
    # labels.json of runs before the gap rule have no through_gap_fraction
    through_gap = sum(view.get("through_gap_fraction", 0.0) for view in views) / len(views)
    gaps = f"; {100 * through_gap:.2f} % dropped, seen through gaps of the rebuilt mesh" if through_gap > 0 else ""
    print(f"esgs labels: {len(views)} views -> {SceneDir(args.scene).prior(PriorSource.LABELS)} "
          f"(filled {100 * filled:.2f} % of pixels, no label {100 * empty:.2f} %{gaps})", file=sys.stderr)
    if result["accuracy"] is not None:
        print(format_accuracy_table(result["accuracy"]))
    return 0
