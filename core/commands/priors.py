"""``esgs priors``: write a scene's prior maps in the standard format (priors/<method>/)."""
from __future__ import annotations

import argparse
import contextlib
import os
import signal
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional

from ..formats.scene_dir import PriorSource, SceneDir, names

HELP = "compute depth/normal prior maps for a scene (priors/<method>/)"

METHODS = names(PriorSource.computed())


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", type=Path, help="scene folder (images/ + sparse/0)")
    parser.add_argument("--method", choices=METHODS, default="sfm",
                        help="sfm: sparse depth from the COLMAP points each view observes; "
                             "ndn: dense relative depth and normals from the NDN diffusion network")
    parser.add_argument("--max-error-px", type=float, default=2.0, help="drop points with a larger reprojection error")
    parser.add_argument("--min-track-length", type=int, default=2, help="drop points seen in fewer views")
    parser.add_argument("--weights", type=Path, default=None,
                        help="ndn: weights file or model folder (default: $ESGS_NDN_WEIGHTS, else the weights "
                             "shipped with the package)")
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
                count, weights = _run_ndn(args, progress) if args.method == "ndn" else (_run_sfm(args, progress), None)
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


def _run_sfm(args: argparse.Namespace, progress) -> int:
    from ..colmap import read_model
    from ..priors.sfm import write_sfm_priors

    model = read_model(args.scene)
    return write_sfm_priors(args.scene, model, progress=progress, max_error_px=args.max_error_px,
                            min_track_length=args.min_track_length)


def _run_ndn(args: argparse.Namespace, progress) -> tuple[int, Path]:
    from ..ndn.infer import write_ndn_priors
    from ..ndn.shipped import resolve_default_weights

    weights = resolve_default_weights(args.weights)
    count = write_ndn_priors(args.scene, weights, steps=args.steps, seed=args.seed, progress=progress)
    return count, weights


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


# --------------------------------------------------------------------------- child process


@dataclass
class PriorsSettings:
    """One priors job (what the Blender add-on and the bench run in a child process)."""

    scene: Path = field(metadata={"help": "scene folder (images/ + sparse/0)"})
    method: str = field(default="sfm", metadata={"help": "prior source to compute", "choices": METHODS})
    max_error_px: float = field(default=2.0, metadata={"help": "sfm: drop points with a larger reprojection error"})
    min_track_length: int = field(default=2, metadata={"help": "sfm: drop points seen in fewer views"})
    weights: Optional[Path] = field(default=None, metadata={"help": "ndn: weights file or model folder (default: shipped)"})
    steps: Optional[int] = field(default=None, metadata={"help": "ndn: DDIM steps (default: the model's)"})
    seed: int = field(default=0, metadata={"help": "ndn: seed of the starting noise"})

    def validate(self) -> None:
        from ..errors import ConfigError

        if self.method not in METHODS:
            raise ConfigError(f"unknown prior method {self.method!r}", hint=f"choose one of {', '.join(METHODS)}")


def child_job(data: dict, context) -> dict:
    """The ``"priors"`` job of the child-process runtime: ``data`` is a :class:`PriorsSettings`
    dict. The runtime turns a stop request into KeyboardInterrupt, on which the writers remove
    their staging folders (the previous priors are kept). Returns ``{"views", "weights", "folder"}``."""
    from ..config import config_from_dict
    from ..progress import ProgressEvent

    settings = config_from_dict(PriorsSettings, data, source=context.config_path)
    # the same argument names as the command line, so both paths share one implementation
    args = argparse.Namespace(**{name: getattr(settings, name) for name in (
        "scene", "method", "max_error_px", "min_track_length", "weights", "steps", "seed")})
    count, weights = _run_ndn(args, context.progress) if settings.method == "ndn" else (
        _run_sfm(args, context.progress), None)
    folder = SceneDir(settings.scene).prior(settings.method)
    line = f"wrote {settings.method} priors for {count} views to {folder}"
    context.progress(ProgressEvent(count, count, f"{settings.method} priors", kind="done", message=line))
    return {"views": count, "weights": None if weights is None else str(weights), "folder": str(folder)}
