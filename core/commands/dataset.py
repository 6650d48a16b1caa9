"""``esgs dataset``: scene folders from real images.

    esgs dataset from-images IMAGES --out SCENE [--matcher exhaustive|sequential] [--single-camera] [--camera-model M]
    esgs dataset from-panorama PANO --out SCENE [--size 1920x1080] [--overlap 0.4] [--fov-deg 60] [--pitch-deg 0 ...]
    esgs dataset rotation-only IMAGES --out SCENE [--focal-px F] [--names a.png b.png ...]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = "build a scene folder from photographs (SfM), a panorama, or a rotation-only station"


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 1920x1080, got {text!r}") from None
    return width, height


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..datasets.sfm import CAMERA_MODELS

    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    images = actions.add_parser("from-images", help="structure from motion (pycolmap, CPU) on a folder of photographs")
    images.add_argument("images", type=Path, help="folder of overlapping photographs")
    images.add_argument("--out", type=Path, required=True, help="scene folder to write (images/, sparse/0, sfm_report.json)")
    images.add_argument("--matcher", choices=("exhaustive", "sequential"), default="exhaustive",
                        help="exhaustive: every pair; sequential: neighbours in name order (long sequences)")
    images.add_argument("--single-camera", action="store_true", help="all images share one camera")
    images.add_argument("--camera-model", choices=CAMERA_MODELS, default="SIMPLE_RADIAL", help="COLMAP camera model to estimate")
    images.add_argument("--camera-params", default="", help="known intrinsics in COLMAP order, comma-separated")
    images.add_argument("--fixed-intrinsics", action="store_true", help="keep --camera-params fixed (calibrated camera)")
    images.add_argument("--verbose", action="store_true", help="show pycolmap's log")
    images.add_argument("--overwrite", action="store_true", help="replace an existing output folder")

    pano = actions.add_parser("from-panorama", help="pinhole views (and their cameras) from an equirectangular panorama or strip")
    pano.add_argument("panorama", type=Path, help="panorama image (2:1 equirectangular, or a flat strip)")
    pano.add_argument("--out", type=Path, required=True, help="scene folder to write")
    pano.add_argument("--size", type=_size, default=(1920, 1080), help="view size WIDTHxHEIGHT (default 1920x1080)")
    pano.add_argument("--overlap", type=float, default=0.4, help="minimum overlap of neighbouring views (0.3-0.6 typical)")
    pano.add_argument("--fov-deg", type=float, default=60.0, help="horizontal field of view of the views, degrees")
    pano.add_argument("--pitch-deg", type=float, action="append", default=None, help="pitch of a row of views (repeat for several rows)")
    kind = pano.add_mutually_exclusive_group()
    kind.add_argument("--equirectangular", dest="equirectangular", action="store_true", default=None,
                      help="treat the image as equirectangular whatever its aspect")
    kind.add_argument("--strip", dest="equirectangular", action="store_false", help="treat the image as a flat strip (crops only)")
    pano.add_argument("--overwrite", action="store_true", help="replace an existing output folder")

    rotation = actions.add_parser("rotation-only", help="one camera station: rotations and focal length from feature matches")
    rotation.add_argument("images", type=Path, help="folder of frames taken from one point (pan/tilt)")
    rotation.add_argument("--out", type=Path, required=True, help="scene folder to write")
    rotation.add_argument("--focal-px", type=float, default=None, help="initial focal length in pixels (default: image width)")
    rotation.add_argument("--fixed-focal", action="store_true", help="keep the focal length fixed")
    rotation.add_argument("--refine-principal-point", action="store_true", help="also refine the principal point")
    rotation.add_argument("--max-features", type=int, default=3000, help="SIFT features per frame")
    rotation.add_argument("--names", nargs="+", default=None, help="use only these file names from the folder")
    rotation.add_argument("--overwrite", action="store_true", help="replace an existing output folder")


def run(args: argparse.Namespace) -> int:
    from ..progress import ConsoleProgress

    bar = ConsoleProgress()
    try:
        if args.action == "from-images":
            from ..datasets.sfm import SfmOptions, scene_from_images

            options = SfmOptions(matcher=args.matcher, single_camera=args.single_camera, camera_model=args.camera_model,
                                  camera_params=args.camera_params, refine_intrinsics=not args.fixed_intrinsics,
                                  verbose=args.verbose, overwrite=args.overwrite)
            report = scene_from_images(args.images, args.out, options, progress=bar)
            shown = {k: v for k, v in report.items() if k != "registered"}
            shown["registered"] = len(report["registered"])
        elif args.action == "from-panorama":
            from ..datasets.panorama import PanoramaOptions, scene_from_panorama

            width, height = args.size
            options = PanoramaOptions(width=width, height=height, overlap=args.overlap, fov_deg=args.fov_deg,
                                      pitches_deg=tuple(args.pitch_deg or (0.0,)), equirectangular=args.equirectangular,
                                      overwrite=args.overwrite)
            report = shown = scene_from_panorama(args.panorama, args.out, options, progress=bar)
        else:
            from ..datasets.rotation import RotationOnlyOptions, scene_from_rotation_only

            options = RotationOnlyOptions(focal_px=args.focal_px, refine_focal=not args.fixed_focal,
                                          refine_principal_point=args.refine_principal_point, max_features=args.max_features,
                                          overwrite=args.overwrite)
            report = scene_from_rotation_only(args.images, args.out, options, progress=bar, names=args.names)
            shown = {k: v for k, v in report.items() if k != "registered"}
            shown["registered"] = len(report["registered"])
    finally:
        bar.close()
    print(json.dumps(shown, indent=2, default=float))
    print(f"wrote scene folder {args.out}")
    return 0
