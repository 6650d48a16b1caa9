"""``esgs priors``: write a scene's prior maps in the standard format (priors/<method>/)."""
from __future__ import annotations

import argparse
import contextlib
import os
import signal
import threading
from pathlib import Path
from typing import Iterator

from ..formats.scene_dir import SceneDir
from ..priors.job import METHODS, PriorsSettings, compute_priors  # noqa: F401 - PriorsSettings: the job's API

HELP = "compute depth/normal prior maps for a scene (priors/<method>/)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", type=Path, help="scene folder (images/ + sparse/0)")
    parser.add_argument("--method", choices=METHODS, default="sfm",
                        help="sfm: sparse depth from the COLMAP points each view observes; "
                             "ndn: dense relative depth and normals from the NDN diffusion network; "
                             "auto: the best of stereo labels, NDN and SfM per pixel with a confidence map, "
                             "computing what is missing (what esgs train --esgs uses; docs/priors.md)")
    parser.add_argument("--force", action="store_true", help="auto: rebuild even when the cached priors/auto holds")
    parser.add_argument("--max-error-px", type=float, default=2.0, help="drop points with a larger reprojection error")
    parser.add_argument("--min-track-length", type=int, default=2, help="drop points seen in fewer views")
    parser.add_argument("--weights", type=Path, default=None,
                        help="ndn: the depth network, a weights file or model folder (default: $ESGS_NDN_WEIGHTS, "
                             "else the one shipped with the package)")
    parser.add_argument("--normal-weights", default=None, metavar="PATH|same",
                        help="ndn: the normals network, a weights file or model folder, or 'same' for the depth "
                             "network's own normals (default: $ESGS_NDN_NORMAL_WEIGHTS, else the completion network "
                             "shipped with the package when the depth network is the shipped one, else 'same')")
    parser.add_argument("--steps", type=int, default=None, help="ndn: DDIM steps (default: the model's)")
    parser.add_argument("--seed", type=int, default=0, help="ndn: seed of the starting noise")
    parser.add_argument("--events", type=Path, default=None,
                        help="also append progress events to this JSON-lines file (what the Blender job runner reads)")


def run(args: argparse.Namespace) -> int:
    from ..errors import ESGSError
    from ..progress import ConsoleProgress, JsonLinesProgress, ProgressEvent, combine

    bar = ConsoleProgress()
    events = JsonLinesProgress(args.events) if args.events is not None else None
    progress = combine(bar, events)
    try:
        with _sigterm_interrupts():
            try:
                count, weights = _compute(args, progress)
            except ESGSError as error:
                # the job runner shows this message rather than guessing from the console output
                if events is not None:
                    events(ProgressEvent(0, 0, f"{args.method} priors", kind="error", message=str(error)))
                raise
        line = f"wrote {args.method} priors for {count} views to {SceneDir(args.scene).prior(args.method)}"
        if weights is not None:
            line += f" (weights: {weights})"
        if events is not None:
            events(ProgressEvent(count, count, f"{args.method} priors", kind="done", message=line))
    finally:
        bar.close()
        if events is not None:
            events.close()
    print(line)
    return 0


def _compute(args: argparse.Namespace, progress) -> tuple[int, "str | None"]:
    settings = PriorsSettings(scene=args.scene, method=args.method, max_error_px=args.max_error_px,
                              min_track_length=args.min_track_length, weights=args.weights,
                              normal_weights=args.normal_weights, steps=args.steps,
                              seed=args.seed, force=args.force)
    return compute_priors(settings, progress)


@contextlib.contextmanager
def _sigterm_interrupts() -> Iterator[None]:
    """Turn SIGTERM (a cancel from Blender's job runner) into KeyboardInterrupt, so the writers'
    clean-up runs (staging folders removed, the previous priors kept) before the process ends."""
    if os.name == "nt" or threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
