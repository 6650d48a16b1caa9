"""One progress protocol for every long job.

A job calls ``progress(ProgressEvent(...))``. The same events feed the CLI progress bar
(:class:`ConsoleProgress`), the JSON-lines file the Blender job runner reads
(:class:`JsonLinesProgress`) and Blender's own progress bar (esgs_addon).
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional


@dataclass
class ProgressEvent:
    """One report from a long job.

    ``step`` counts from 0 to ``total``; ``stage`` names the phase ("train", "eval",
    "render"...); ``metrics`` holds numbers such as loss, psnr, n_gaussians, eta_s;
    ``kind`` is "progress", "message", "eval", "done" or "error". An "eval" event is a point of
    a training run's evaluation curve (``TrainConfig.eval_every``): stage "eval", ``step`` the
    training step, ``metrics`` the held-out psnr and ssim, train_s (training seconds so far,
    evaluations excluded) and n_gaussians.
    """

    step: int
    total: int
    stage: str = ""
    metrics: dict[str, float] = field(default_factory=dict)
    kind: str = "progress"
    message: str = ""
    time: float = field(default_factory=time.time)

    def to_json(self) -> str:
        return json.dumps(asdict(self), default=float)

    @staticmethod
    def from_json(line: str) -> "ProgressEvent":
        data = json.loads(line)
        return ProgressEvent(**data)


ProgressCallback = Callable[[ProgressEvent], None]


def no_progress(event: ProgressEvent) -> None:
    """A callback that ignores every event."""


class JsonLinesProgress:
    """Append each event as one JSON line and flush, so a reader can follow live."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._handle = open(self.path, "a", encoding="utf-8", buffering=1)

    def __call__(self, event: ProgressEvent) -> None:
        self._handle.write(event.to_json() + "\n")
        self._handle.flush()

    def close(self) -> None:
        self._handle.close()


class ConsoleProgress:
    """A tqdm bar per stage showing the event's metrics."""

    def __init__(self, stream: Any = None, min_interval_s: float = 0.2):
        self.stream = stream or sys.stderr
        self.min_interval_s = min_interval_s
        self._bar = None
        self._stage: Optional[str] = None

    def __call__(self, event: ProgressEvent) -> None:
        from tqdm import tqdm

        if event.kind == "message":
            (tqdm.write if self._bar else print)(event.message, file=self.stream)
            return
        if event.kind == "eval":  # a line beside the training bar, which goes on
            metrics = event.metrics
            line = (f"step {event.step}: held-out PSNR {_short(metrics.get('psnr'))} dB, "
                    f"SSIM {_short(metrics.get('ssim'))} after {_short(metrics.get('train_s'))} s of training")
            (tqdm.write if self._bar else print)(line, file=self.stream)
            return
        if self._bar is None or event.stage != self._stage or event.total != self._bar.total:
            self.close()
            self._stage = event.stage
            self._bar = tqdm(total=event.total, desc=event.stage or None, file=self.stream,
                             mininterval=self.min_interval_s, dynamic_ncols=True)
        self._bar.n = event.step
        if event.metrics:
            self._bar.set_postfix({k: _short(v) for k, v in event.metrics.items()}, refresh=False)
        self._bar.refresh()
        if event.kind in ("done", "error"):
            self.close()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def _short(value: float) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def combine(*callbacks: Optional[ProgressCallback]) -> ProgressCallback:
    """One callback that forwards each event to every non-None callback."""
    active = [cb for cb in callbacks if cb is not None]

    def forward(event: ProgressEvent) -> None:
        for callback in active:
            callback(event)

    return forward
