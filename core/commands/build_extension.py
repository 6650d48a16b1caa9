"""``esgs build-extension``: the installable Blender extension zip ("Install from Disk")."""
from __future__ import annotations

import argparse
from pathlib import Path

NAME = "build-extension"
HELP = "validate and build the Blender extension zip with its bundled wheels"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("dist"), help="output folder (default: dist)")
    parser.add_argument("--platform", default="linux-x64",
                        help="linux-x64, windows-x64, macos-arm64, or 'all' for one zip per platform")
    parser.add_argument("--wheel-cache", type=Path, default=None, help="folder of cached wheels")


def run(args: argparse.Namespace) -> int:
    from ..apps.packaging import build_extension

    platform = None if args.platform == "all" else args.platform
    for path in build_extension(args.out, platform=platform, wheel_cache=args.wheel_cache):
        print(path)
    return 0
