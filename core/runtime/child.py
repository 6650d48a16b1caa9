"""The child side of the runtime: ``python -m esgs.core.runtime.child JOB CONFIG.json ...``.

It reads the job's config file (a JSON object written from the job's settings dataclass),
runs the job's registered function (:mod:`.entry_points`), appends its progress events to
``--events`` as JSON lines and writes ``--result``: ``{"status": "ok", "result": ...}``, or
``{"status": "error", "error": {"type", "message", "path", "hint"}}`` for a handled error
(our :mod:`esgs.core.errors` types), or ``{"status": "cancelled"}``. The parent raises the
error again as the same type (:func:`error_from_dict`).

Cancellation is a stop file (``--stop-file``), which works on every platform: a job that
watches it itself (the trainer, which checkpoints first) gets its path in
``context.stop_file``; for every other job a watcher thread here turns its appearance,
like SIGTERM, into a KeyboardInterrupt in the job's thread so its clean-up runs.

Exit status: 0 done, 2 handled error, 130 cancelled; anything else is a crash (the parent
reports the child's last output lines).
"""
from __future__ import annotations

import _thread
import argparse
import os
import signal
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

from ..errors import CheckpointError, ConfigError, DatasetError, ESGSError, FormatError
from ..io_utils import atomic_write_json
from ..progress import JsonLinesProgress, ProgressCallback, ProgressEvent, no_progress
from . import entry_points

EXIT_OK, EXIT_ERROR, EXIT_CANCELLED = 0, 2, 130

#: the error types a child may report that the parent raises as themselves (others: ESGSError)
ERROR_TYPES: dict[str, type[ESGSError]] = {cls.__name__: cls for cls in
                                           (ESGSError, DatasetError, ConfigError, CheckpointError, FormatError)}


@dataclass
class ChildContext:
    """What a child-side job function gets besides its config data.

    ``progress`` appends to the parent's events file; ``stop_file`` appears when the parent
    asks the job to stop (None when started without one); ``config_path`` is the config
    file (for error messages); ``events_path``: the file ``progress`` appends to (None: none).
    """

    progress: ProgressCallback
    stop_file: Optional[Path]
    config_path: Path
    events_path: Optional[Path] = None

    def stop_requested(self) -> bool:
        """Whether the parent has asked the job to stop."""
        return self.stop_file is not None and self.stop_file.exists()


def error_to_dict(error: ESGSError) -> dict[str, Any]:
    """The JSON form of one of our errors: its type name, message, path and hint."""
    return {"type": type(error).__name__, "message": getattr(error, "message", str(error)),
            "path": None if error.path is None else str(error.path), "hint": error.hint}


def error_from_dict(data: dict[str, Any]) -> ESGSError:
    """The error :func:`error_to_dict` describes, as the same type where it is one of ours."""
    cls = ERROR_TYPES.get(str(data.get("type", "")), ESGSError)
    return cls(str(data.get("message") or "the child process failed"), path=data.get("path"), hint=data.get("hint"))


def read_config_data(path: str | os.PathLike) -> dict[str, Any]:
    """The JSON object of a job's config file.

    Raises:
        ConfigError: the file is missing, not JSON, or not an object.
    """
    from ..config import read_json_object

    return read_json_object(path, what="job config file")


class _StopWatcher:
    """Turn the stop file's appearance (and SIGTERM) into KeyboardInterrupt in the main thread."""

    def __init__(self, stop_file: Optional[Path], poll_s: float = 0.2):
        self.stop_file = stop_file
        self.poll_s = poll_s
        self.requested = False
        self._done = threading.Event()
        self._previous_handler: Any = None

    def __enter__(self) -> "_StopWatcher":
        if self.stop_file is not None:
            threading.Thread(target=self._watch, name="esgs-stop-watcher", daemon=True).start()
        if os.name != "nt" and threading.current_thread() is threading.main_thread():
            self._previous_handler = signal.signal(signal.SIGTERM, self._on_signal)
        return self

    def _watch(self) -> None:
        assert self.stop_file is not None
        while not self._done.wait(self.poll_s):
            if self.stop_file.exists():
                self.requested = True
                _thread.interrupt_main()
                return

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.requested = True
        raise KeyboardInterrupt

    def __exit__(self, *exc: Any) -> None:
        self._done.set()
        if self._previous_handler is not None:
            signal.signal(signal.SIGTERM, self._previous_handler)


def run_child_job(job: str, config_path: Path, *, events: Optional[Path] = None, result: Optional[Path] = None,
                  stop_file: Optional[Path] = None) -> int:
    """Run ``job`` with the config file ``config_path``; returns the exit status (see the module docstring)."""
    progress_file = JsonLinesProgress(events) if events is not None else None
    progress: ProgressCallback = progress_file if progress_file is not None else no_progress
    package = __package__.rsplit(".core.runtime", 1)[0] if __package__ else entry_points.PACKAGE
    context = ChildContext(progress=progress, stop_file=stop_file, config_path=Path(config_path),
                           events_path=Path(events) if events is not None else None)

    def finish(record: dict[str, Any]) -> None:
        if result is not None:
            atomic_write_json(result, record)

    try:
        if stop_file is not None and stop_file.exists():
            stop_file.unlink()  # a request left by an earlier run must not stop this one
        entry = entry_points.entry_point(job)
        data = read_config_data(config_path)
        function = entry_points.load_job_function(job, package)
        if entry.watches_stop_file:
            value = function(data, context)
        else:
            with _StopWatcher(stop_file):
                value = function(data, context)
    except ESGSError as error:
        # the job runner shows this message rather than guessing from the console output
        progress(ProgressEvent(0, 0, job, kind="error", message=str(error)))
        finish({"status": "error", "error": error_to_dict(error)})
        print(f"esgs {job}: error: {error}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        progress(ProgressEvent(0, 0, job, kind="message", message="stopped on request"))
        finish({"status": "cancelled"})
        return EXIT_CANCELLED
    finally:
        if progress_file is not None:
            progress_file.close()
    finish({"status": "ok", "result": value})
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m esgs.core.runtime.child",
                                     description="run one registered job from its JSON config file")
    parser.add_argument("job", help=f"job name ({', '.join(sorted(entry_points.ENTRY_POINTS))})")
    parser.add_argument("config", type=Path, help="the job's JSON config file")
    parser.add_argument("--events", type=Path, default=None, help="append progress events to this JSON-lines file")
    parser.add_argument("--result", type=Path, default=None, help="write the result or error here (JSON)")
    parser.add_argument("--stop-file", type=Path, default=None, help="stop the job when this file appears")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m esgs.core.runtime.child``; returns the exit status."""
    args = build_parser().parse_args(argv)
    return run_child_job(args.job, args.config, events=args.events, result=args.result, stop_file=args.stop_file)


if __name__ == "__main__":
    sys.exit(main())
