"""``esgs demo``: the main job end to end on the CPU (scene, auto priors, ESGS and 3DGS, Blender, report)."""
from __future__ import annotations

import argparse

HELP = ("run the main job end to end: synthetic scene, auto priors (stereo labels, NDN and SfM), ESGS vs 3DGS "
        "training, Blender heat map, report")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..config import add_dataclass_arguments
    from ..apps.demo import DemoConfig

    add_dataclass_arguments(parser, DemoConfig)
    parser.add_argument("--quick", action="store_true", help="a tiny run (minutes) to check the set-up")


def run(args: argparse.Namespace) -> int:
    from ..config import dataclass_from_args
    from ..apps.demo import DemoConfig, run_demo
    from ..progress import ConsoleProgress

    base = DemoConfig(views=6, width=160, height=90, iterations=150, samples=8, snapshots=3) if args.quick else None
    config = dataclass_from_args(DemoConfig, args, base=base)
    console = ConsoleProgress()
    try:
        report = run_demo(config, progress=console)
    finally:
        console.close()
    print(f"report: {report}")
    return 0
