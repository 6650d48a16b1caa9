"""Stop requests for long loops: SIGTERM or Ctrl-C ends the loop between steps, not inside one.

A training loop checks :attr:`StopRequests.signal_name` after each step and, when it is set,
saves a checkpoint and returns, so ``--resume`` continues where it stopped. A second Ctrl-C
stops at once (KeyboardInterrupt). Handlers are installed in the main thread only (Python
allows no other) and restored on exit.
"""
from __future__ import annotations

import signal
import threading
from typing import Any, Optional


class StopRequests:
    """Turns SIGTERM/SIGINT into a flag checked between steps (main thread only)."""

    def __init__(self) -> None:
        #: The signal's name once one arrived (or a caller's reason, e.g. "stop request"); None before.
        self.signal_name: Optional[str] = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> "StopRequests":
        if threading.current_thread() is threading.main_thread():
            for number in (signal.SIGTERM, signal.SIGINT):
                self._previous[number] = signal.signal(number, self._handle)
        return self

    def _handle(self, number: int, frame: Any) -> None:
        if self.signal_name is not None and number == signal.SIGINT:
            raise KeyboardInterrupt  # a second Ctrl-C stops at once
        self.signal_name = signal.Signals(number).name

    def __exit__(self, *exc: Any) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)
        self._previous.clear()
