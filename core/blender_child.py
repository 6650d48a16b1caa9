"""The line protocol between a command in ``core`` and the Blender child process it starts.

``core`` never imports ``bpy``, so work that needs Blender (``esgs scene``, ``esgs labels``)
runs ``python -m esgs.esgs_addon.<module> ... --events-stdout`` in a child process. The child
prints one line ``ESGS_EVENT <json>`` per progress event and, on a handled failure, one line
``ESGS_ERROR {"type": ..., "message": ...}`` before exiting with a non-zero status; every
other line is Blender's own log. The child side writes these lines with :func:`print_event`
and :func:`print_error` (or :func:`report_error`); the parent side reads them with
:func:`run_child`.
"""
from __future__ import annotations

import json
import subprocess
import sys

from .errors import ConfigError, DatasetError, ESGSError
from .progress import ProgressCallback, ProgressEvent

EVENT_PREFIX = "ESGS_EVENT "
ERROR_PREFIX = "ESGS_ERROR "

# the errors a child may name that the parent raises as themselves (any other: ESGSError)
_ERROR_TYPES: dict[str, type[ESGSError]] = {"ConfigError": ConfigError, "DatasetError": DatasetError}


def print_event(event: ProgressEvent) -> None:
    """Child side: write one progress event line on stdout (flushed, so the parent sees it now)."""
    print(EVENT_PREFIX + event.to_json(), flush=True)


def print_error(error: BaseException) -> None:
    """Child side: write the error line the parent raises again as ``type(error)`` where it can."""
    print(ERROR_PREFIX + json.dumps({"type": type(error).__name__, "message": str(error)}), flush=True)


def report_error(error: BaseException, *, program: str, events_stdout: bool) -> int:
    """Child side: report a handled failure, as the error line for the parent with
    ``events_stdout``, else as ``"<program>: error: ..."`` on stderr; returns exit status 2."""
    if events_stdout:
        print_error(error)
    else:
        print(f"{program}: error: {error}", file=sys.stderr)
    return 2


def run_child(command: list[str], progress: ProgressCallback, *, verbose: bool = False,
              task: str = "Blender child process") -> None:
    """Run a Blender child process to its end, relaying its progress events to ``progress``.

    Lines that are not ours are Blender's log: shown on stderr only with ``verbose``. The
    child's reported error is raised here as our error of the same type (ConfigError,
    DatasetError, else ESGSError); a child that dies without one raises ESGSError with its
    exit status. ``task`` names the work in those messages (``"scene generation"``).
    """
    error: dict[str, str] | None = None
    with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1) as child:
        assert child.stdout is not None
        for line in child.stdout:
            if line.startswith(EVENT_PREFIX):
                progress(ProgressEvent.from_json(line[len(EVENT_PREFIX):]))
            elif line.startswith(ERROR_PREFIX):
                error = json.loads(line[len(ERROR_PREFIX):])
            elif verbose:
                print(line, end="", file=sys.stderr)
        status = child.wait()
    if error is not None:
        raise _ERROR_TYPES.get(error.get("type", ""), ESGSError)(error.get("message", f"{task} failed"))
    if status != 0:
        raise ESGSError(f"{task} failed (exit status {status})", hint="run again with --verbose to see Blender's log")
