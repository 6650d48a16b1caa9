"""``esgs colmap``: check, convert and undistort COLMAP scenes.

    esgs colmap check SCENE [--sizes]          validate a model (and its images) and summarise it
    esgs colmap convert MODEL OUT [--text]     rewrite a model as binary (or text)
    esgs colmap undistort SCENE OUT [--keep-size]  PINHOLE cameras and undistorted images
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = "check, convert (bin/txt) or undistort a COLMAP scene"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    check = actions.add_parser("check", help="validate a model and its images, print a summary")
    check.add_argument("scene", type=Path, help="scene folder (images/ + sparse/0) or model folder")
    check.add_argument("--images", type=Path, default=None, help="image folder (default: SCENE/images when it exists)")
    check.add_argument("--sizes", action="store_true", help="also decode every image and compare its size with its camera")
    check.add_argument("--json", action="store_true", help="print the summary as JSON")

    convert = actions.add_parser("convert", help="write a model in binary (default) or text form")
    convert.add_argument("model", type=Path, help="model folder or scene folder")
    convert.add_argument("out", type=Path, help="output model folder (written atomically)")
    convert.add_argument("--text", action="store_true", help="write .txt files instead of .bin")
    convert.add_argument("--overwrite", action="store_true", help="replace an existing non-empty output folder")

    undistort = actions.add_parser("undistort", help="write an undistorted scene with PINHOLE cameras")
    undistort.add_argument("scene", type=Path, help="scene folder (images/ + sparse/0)")
    undistort.add_argument("out", type=Path, help="output scene folder (written atomically)")
    undistort.add_argument("--keep-size", action="store_true", help="keep image size and intrinsics (black corners possible)")
    undistort.add_argument("--overwrite", action="store_true", help="replace an existing output folder")


def summary(model) -> dict[str, object]:
    """Counts and camera models of a :class:`ColmapModel`, as plain data."""
    _, _, errors, track_lengths = model.points_arrays()
    return {
        "source": model.source,
        "cameras": {camera_id: f"{c.model} {c.width}x{c.height}" for camera_id, c in sorted(model.cameras.items())},
        "images": len(model.images),
        "points": len(model.points),
        "observations": int(track_lengths.sum()),
        "mean_track_length": float(track_lengths.mean()) if len(track_lengths) else 0.0,
        "mean_reprojection_error_px": float(errors.mean()) if len(errors) else 0.0,
    }


def run(args: argparse.Namespace) -> int:
    from ..colmap import check_image_sizes, load_scene, read_model, undistort_model, validate_images, write_model
    from ..progress import ConsoleProgress
    from ..formats.scene_dir import SceneDir

    if args.action == "check":
        model = read_model(args.scene)
        scene_images = SceneDir(args.scene).images
        images_dir = args.images or (scene_images if scene_images.is_dir() else None)
        if images_dir is not None:
            validate_images(model, images_dir)
            if args.sizes:
                check_image_sizes(model, images_dir)
        info = summary(model)
        info["images_checked"] = str(images_dir) if images_dir is not None else "no image folder given"
        if args.json:
            print(json.dumps(info, indent=2))
        else:
            for key, value in info.items():
                print(f"{key}: {value}")
        return 0
    if args.action == "convert":
        model = read_model(args.model)
        write_model(model, args.out, binary=not args.text, overwrite=args.overwrite)
        print(f"wrote {'text' if args.text else 'binary'} model with {len(model.images)} images to {args.out}")
        return 0
    model, images_dir = load_scene(args.scene)
    undistort_model(model, images_dir, args.out, keep_size=args.keep_size, overwrite=args.overwrite, progress=ConsoleProgress())
    print(f"wrote undistorted scene to {args.out}")
    return 0
