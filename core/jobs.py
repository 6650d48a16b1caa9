"""Run the trainer in a separate process and follow its progress.

Training needs torch and minutes to hours of CPU/GPU time, so Blender never trains in its
own process: :class:`TrainingJob` starts ``python -m esgs.core.cli train ...`` (or any
command with the same arguments), tails the JSON-lines events the trainer writes
(:class:`esgs.core.progress.ProgressEvent`) on a reader thread, and keeps the latest
state for a UI timer or a blocking loop to show. ``cancel()`` sends SIGTERM so the trainer
can save a checkpoint; ``resume()`` starts it again with ``--resume``.

Plain Python, no bpy: the Blender operators and headless scripts both use it.
"""
from __future__ import annotations

import atexit
import collections
import dataclasses
import importlib.util
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

from .errors import ConfigError, ESGSError
from .progress import ProgressEvent

#: Status values of a job, in the order a job passes through them.
PENDING, RUNNING, FINISHED, FAILED, CANCELLED = "pending", "running", "finished", "failed", "cancelled"
ACTIVE_STATUSES = (PENDING, RUNNING)

_PACKAGE_ROOT = Path(__file__).resolve().parents[1]


@dataclasses.dataclass
class JobState:
    """A snapshot of a job, safe to read from any thread (the job hands out copies).

    ``step``/``total`` come from the latest progress event; ``loss``, ``psnr``,
    ``n_gaussians`` and ``eta_s`` from its metrics (None until the trainer reports them).
    ``error`` is set when ``status`` is ``"failed"``: the trainer's "error" event message,
    or the last lines it printed.
    """

    status: str = PENDING
    step: int = 0
    total: int = 0
    stage: str = ""
    loss: Optional[float] = None
    psnr: Optional[float] = None
    n_gaussians: Optional[int] = None
    eta_s: Optional[float] = None
    message: str = ""
    error: str = ""
    returncode: Optional[int] = None
    started_at: Optional[float] = None
    ended_at: Optional[float] = None
    events_seen: int = 0

    @property
    def fraction(self) -> float:
        """Progress in [0, 1] (0 while the total is unknown)."""
        if self.total <= 0:
            return 0.0
        return min(max(self.step / self.total, 0.0), 1.0)

    @property
    def active(self) -> bool:
        return self.status in ACTIVE_STATUSES

    def summary(self) -> str:
        """One line for a status bar or a console: ``step 120/500 loss 0.0312 ...``."""
        parts = [self.status]
        if self.total:
            parts.append(f"step {self.step}/{self.total}")
        if self.loss is not None:
            parts.append(f"loss {self.loss:.4g}")
        if self.psnr is not None:
            parts.append(f"PSNR {self.psnr:.2f} dB")
        if self.n_gaussians is not None:
            parts.append(f"{self.n_gaussians:,} Gaussians")
        if self.eta_s is not None and self.active:
            parts.append(f"ETA {format_duration(self.eta_s)}")
        if self.error:
            parts.append(f"error: {self.error}")
        return "  ".join(parts)


def format_duration(seconds: float) -> str:
    """``3725`` -> ``"1:02:05"``; ``65`` -> ``"1:05"``."""
    seconds = max(int(round(seconds)), 0)
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


# --------------------------------------------------------------------------- interpreter


def _venv_python(venv: Path) -> Path:
    return venv / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def find_python(preferred: str | os.PathLike | None = None) -> str:
    """The Python interpreter that runs the trainer.

    Blender's own ``sys.executable`` has no torch, so the search is: ``preferred`` (the
    add-on preference) when set, ``$ESGS_PYTHON``, the project's virtual environment
    ``<package root>/.venv`` (a development checkout linked into Blender), then the
    running interpreter when it can import torch (plain Python, the bpy module). Falls
    back to the running interpreter; the trainer then fails with an import error that
    the job reports.

    Raises:
        ConfigError: ``preferred`` or ``$ESGS_PYTHON`` names a file that does not exist.
    """
    for source, value in (("the add-on preference", preferred), ("$ESGS_PYTHON", os.environ.get("ESGS_PYTHON"))):
        if value:
            path = Path(value).expanduser()
            if not path.is_file():
                raise ConfigError(f"the Python interpreter set in {source} does not exist", path=path,
                                  hint="point it at the python of a virtual environment that has torch and esgs")
            return str(path)
    venv_python = _venv_python(_PACKAGE_ROOT / ".venv")
    if venv_python.is_file():
        return str(venv_python)
    return sys.executable


def trainer_command(python: str | None = None) -> list[str]:
    """The command prefix that runs the trainer: ``[python, -m, esgs.core.cli, train]``."""
    return [python or find_python(), "-m", "esgs.core.cli", "train"]


def trainer_options() -> set[str]:
    """The long options (``--depth``...) the installed ``esgs train`` accepts; empty if absent.

    The Blender side offers a switch only when the trainer has it, so the UI never sends
    an option the trainer would reject.
    """
    try:
        from .cli import build_parser

        parser = build_parser()
    except Exception:  # noqa: BLE001 - a broken command module must not break the UI
        return set()
    for action in parser._actions:  # argparse keeps subparsers here; no public accessor
        choices = getattr(action, "choices", None)
        if isinstance(choices, dict) and "train" in choices:
            return {s for a in choices["train"]._actions for s in a.option_strings if s.startswith("--")}
    return set()


def trainer_available() -> bool:
    """Whether the engine's trainer module is installed (``esgs.core.train``)."""
    try:
        return importlib.util.find_spec(f"{__package__}.train") is not None
    except (ImportError, ValueError):
        return False


# --------------------------------------------------------------------------- the job


class TrainingJob:
    """One training run in a child process.

    The child is ``trainer + [scene_dir, --out, run_dir, --iterations, N, --events, events]
    + extra_args`` (plus ``--resume`` for :meth:`resume`). ``trainer`` defaults to
    :func:`trainer_command`; tests pass a small fake script with the same interface.

    Args:
        scene_dir: the COLMAP scene folder to train on.
        run_dir: where the trainer writes checkpoints and ``point_cloud.ply``.
        iterations: number of training steps.
        extra_args: further trainer options (``["--depth", "--priors", "gt"]``).
        events_path: the JSON-lines progress file; ``<run_dir>/events.jsonl`` by default.
        python: interpreter for the default trainer command (see :func:`find_python`).
        threads: CPU threads for the child (``OMP_NUM_THREADS`` and friends); 0 keeps the default.
        on_output: called with every line the child prints (stdout and stderr merged),
            e.g. ``print`` for a headless run; called from the reader thread.
        env: extra environment variables for the child.
    """

    def __init__(self, scene_dir: str | os.PathLike, run_dir: str | os.PathLike, *, iterations: int,
                 extra_args: Sequence[str] = (), events_path: str | os.PathLike | None = None,
                 trainer: Sequence[str] | None = None, python: str | None = None, threads: int = 0,
                 on_output: Optional[Callable[[str], None]] = None, env: Optional[dict[str, str]] = None):
        if iterations <= 0:
            raise ConfigError(f"iterations must be positive, got {iterations}")
        self.scene_dir = Path(scene_dir)
        self.run_dir = Path(run_dir)
        self.iterations = int(iterations)
        self.extra_args = [str(a) for a in extra_args]
        self.events_path = Path(events_path) if events_path else self.run_dir / "events.jsonl"
        self.trainer = list(trainer) if trainer else trainer_command(python)
        self.threads = int(threads)
        self.on_output = on_output
        self.env = dict(env or {})
        self.output_tail: collections.deque[str] = collections.deque(maxlen=200)
        self._state = JobState()
        self._lock = threading.Lock()
        self._process: Optional[subprocess.Popen] = None
        self._threads: list[threading.Thread] = []
        self._finished = threading.Event()
        self._finished.set()  # nothing running yet: wait() returns at once
        self._cancel_requested = False
        self._done_event_seen = False
        self._error_event_message = ""

    # -- public API ---------------------------------------------------------------

    def command(self, resume: bool = False) -> list[str]:
        """The full command line the child runs."""
        args = [str(self.scene_dir), "--out", str(self.run_dir), "--iterations", str(self.iterations),
                "--events", str(self.events_path)]
        if resume:
            args.append("--resume")
        return self.trainer + args + self.extra_args

    def start(self, resume: bool = False) -> "TrainingJob":
        """Start the child process; returns at once. Raises ESGSError if already running."""
        with self._lock:
            if self._state.active and self._process is not None:
                raise ESGSError("this training job is already running", path=self.run_dir,
                                hint="cancel it first or wait for it to finish")
            if not self.scene_dir.exists():
                raise ConfigError("the scene folder does not exist", path=self.scene_dir,
                                  hint="import a COLMAP scene or choose its folder")
            self._state = JobState(status=RUNNING, total=self.iterations, started_at=time.time())
            self._cancel_requested = False
            self._done_event_seen = False
            self._error_event_message = ""
            self.output_tail.clear()
            self._finished.clear()
        self.events_path.parent.mkdir(parents=True, exist_ok=True)
        # Events of earlier runs (the trainer appends on resume) are skipped by starting
        # at the file's current end.
        start_offset = self.events_path.stat().st_size if self.events_path.exists() else 0
        try:
            self._process = subprocess.Popen(
                self.command(resume), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT, env=self._child_env(), cwd=str(self.run_dir.parent),
                # a new session keeps a Ctrl-C in Blender's console from killing the trainer
                # mid-write; cancel() and the exit handler stop it cleanly instead
                start_new_session=(os.name != "nt"),
            )
        except OSError as err:
            self._finish(FAILED, error=f"could not start the trainer ({self.trainer[0]}): {err}")
            raise ESGSError(f"could not start the trainer: {err}", path=self.trainer[0],
                            hint="check the Python interpreter in the add-on preferences") from err
        _register_live(self)
        output_thread = threading.Thread(target=self._read_output, name="esgs-job-output", daemon=True)
        watcher = threading.Thread(target=self._watch, args=(start_offset,), name="esgs-job-events", daemon=True)
        self._threads = [output_thread, watcher]
        for thread in self._threads:
            thread.start()
        return self

    def resume(self) -> "TrainingJob":
        """Start again from the trainer's last checkpoint (``--resume``)."""
        return self.start(resume=True)

    def state(self) -> JobState:
        """A copy of the latest state."""
        with self._lock:
            return dataclasses.replace(self._state)

    @property
    def running(self) -> bool:
        return not self._finished.is_set()

    def wait(self, timeout: float | None = None, *, poll_s: float = 0.5,
             on_update: Optional[Callable[[JobState], None]] = None) -> JobState:
        """Block until the job ends (or ``timeout`` seconds pass); returns the state.

        ``on_update`` is called from this thread whenever a new event arrived, so a
        headless run can print progress. Ctrl-C or SIGTERM cancels the trainer (it
        checkpoints) before the KeyboardInterrupt / SystemExit(143) propagates.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        seen = -1
        previous = _raise_on_sigterm()
        try:
            while True:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    break
                ended = self._finished.wait(poll_s if remaining is None else min(poll_s, remaining))
                state = self.state()
                if on_update is not None and (state.events_seen != seen or ended):
                    seen = state.events_seen
                    on_update(state)
                if ended:
                    break
        except (KeyboardInterrupt, _Terminated):
            # a killed script must not leave the trainer running on its own
            self.cancel()
            raise
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
        return self.state()

    def cancel(self, timeout: float = 120.0, *, wait: bool = True) -> JobState:
        """Ask the trainer to stop (SIGTERM: it saves a checkpoint); kill it if it hangs.

        With ``wait=False`` (a UI button) this returns at once; the job's status turns to
        ``"cancelled"`` when the child has exited, and a watchdog kills it after ``timeout``.
        """
        process = self._process
        if process is None or process.poll() is not None:
            self._finished.wait(5.0)
            return self.state()
        self._cancel_requested = True
        if not wait:
            threading.Thread(target=_terminate, args=(process, timeout), name="esgs-job-cancel", daemon=True).start()
            return self.state()
        _terminate(process, timeout)
        self._finished.wait(timeout)
        return self.state()

    # -- internals ----------------------------------------------------------------

    def _child_env(self) -> dict[str, str]:
        env = dict(os.environ)
        env.update(self.env)
        env["PYTHONUNBUFFERED"] = "1"
        if self.threads > 0:
            for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "ESGS_THREADS"):
                env[name] = str(self.threads)
        # An installed extension lives in a folder named after its id ("esgs"): putting
        # its parent on the path lets the child import the very same engine.
        if _PACKAGE_ROOT.name == "esgs":
            env["PYTHONPATH"] = os.pathsep.join(p for p in (str(_PACKAGE_ROOT.parent), env.get("PYTHONPATH")) if p)
        # Blender sets PYTHONHOME/PYTHONPATH for its bundled Python; another interpreter
        # must not inherit PYTHONHOME.
        env.pop("PYTHONHOME", None)
        return env

    def _read_output(self) -> None:
        process = self._process
        assert process is not None and process.stdout is not None
        for raw in iter(process.stdout.readline, b""):
            # tqdm redraws with carriage returns; keep only the last redraw of a line
            line = raw.decode("utf-8", errors="replace").rstrip("\r\n").split("\r")[-1]
            if not line.strip():
                continue
            self.output_tail.append(line)
            if self.on_output is not None:
                try:
                    self.on_output(line)
                except Exception:  # noqa: BLE001 - a display callback must not kill the reader
                    pass
        process.stdout.close()

    def _watch(self, offset: int) -> None:
        process = self._process
        assert process is not None
        pending = b""
        while True:
            returncode = process.poll()
            offset, pending = self._read_events(offset, pending)
            if returncode is not None:
                break
            time.sleep(0.1)
        self._threads[0].join(timeout=5.0)  # the last output lines explain a failure
        self._read_events(offset, pending + b"\n" if pending else b"")
        if self._cancel_requested and not self._done_event_seen:
            self._finish(CANCELLED, returncode=returncode)
        elif returncode == 0 and not self._error_event_message:
            self._finish(FINISHED, returncode=returncode)
        else:
            self._finish(FAILED, returncode=returncode, error=self._failure_message(returncode))

    def _failure_message(self, returncode: int) -> str:
        if self._error_event_message:
            return self._error_event_message
        lines = [line for line in self.output_tail if line.strip()]
        # the last traceback line ("ModuleNotFoundError: No module named 'torch'") or the
        # CLI's "esgs train: error: ..." line says what went wrong
        for line in reversed(lines):
            if "error" in line.lower() or "exception" in line.lower():
                if line.startswith("ModuleNotFoundError"):
                    # the usual cause: Blender's own Python, which has no torch
                    return (f"{line.strip()} (the trainer ran with {self.trainer[0]}; set a Python that has "
                            "torch and esgs in the add-on preferences or $ESGS_PYTHON)")
                return line.strip()
        if lines:
            return lines[-1].strip()
        return f"the trainer exited with code {returncode}"

    def _read_events(self, offset: int, pending: bytes) -> tuple[int, bytes]:
        try:
            with open(self.events_path, "rb") as handle:
                handle.seek(offset)
                chunk = handle.read()
        except FileNotFoundError:
            return offset, pending
        if not chunk and not pending.endswith(b"\n"):
            return offset, pending
        offset += len(chunk)
        data = pending + chunk
        *lines, pending = data.split(b"\n")  # the last piece may be a line still being written
        for line in lines:
            if line.strip():
                self._apply_event(line.decode("utf-8", errors="replace"))
        return offset, pending

    def _apply_event(self, line: str) -> None:
        try:
            data = json.loads(line)
            if not isinstance(data, dict):
                return
            event = ProgressEvent(step=int(data.get("step", 0)), total=int(data.get("total", 0)),
                                  stage=str(data.get("stage", "")), metrics=dict(data.get("metrics") or {}),
                                  kind=str(data.get("kind", "progress")), message=str(data.get("message", "")))
        except (ValueError, TypeError):
            return  # a torn or foreign line is not worth failing the job over
        with self._lock:
            state = self._state
            state.events_seen += 1
            state.step, state.stage = event.step, event.stage
            if event.total:
                state.total = event.total
            metrics = event.metrics
            if "loss" in metrics:
                state.loss = _number(metrics["loss"])
            if "psnr" in metrics:
                state.psnr = _number(metrics["psnr"])
            if "n_gaussians" in metrics:
                count = _number(metrics["n_gaussians"])
                state.n_gaussians = int(count) if count is not None else None
            if "eta_s" in metrics:
                state.eta_s = _number(metrics["eta_s"])
            if event.message:
                state.message = event.message
            if event.kind == "done":
                self._done_event_seen = True
            elif event.kind == "error":
                self._error_event_message = event.message or "the trainer reported an error"

    def _finish(self, status: str, *, returncode: int | None = None, error: str = "") -> None:
        with self._lock:
            self._state.status = status
            self._state.returncode = returncode
            self._state.error = error
            self._state.ended_at = time.time()
            if status == FINISHED and self._state.total:
                self._state.step = max(self._state.step, self._state.total)
        _unregister_live(self)
        self._finished.set()


class _Terminated(SystemExit):
    """SIGTERM received while blocking in :meth:`TrainingJob.wait` (exit status 143)."""


def _raise_on_sigterm():
    """In the main thread, turn SIGTERM into :class:`_Terminated`; returns the old handler."""
    if threading.current_thread() is not threading.main_thread() or os.name == "nt":
        return None

    def handler(signum, frame):
        raise _Terminated(128 + signum)

    try:
        return signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main interpreter
        return None


def _number(value: object) -> Optional[float]:
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None


def _terminate(process: subprocess.Popen, timeout: float) -> None:
    """SIGTERM (graceful: the trainer checkpoints), then SIGKILL after ``timeout`` seconds."""
    try:
        if os.name == "nt":
            process.terminate()
        else:
            process.send_signal(signal.SIGTERM)
        process.wait(timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(10.0)
    except (ProcessLookupError, OSError):
        pass


# --------------------------------------------------------------------------- registry


_LIVE: set[TrainingJob] = set()
_LIVE_LOCK = threading.Lock()
_JOBS: dict[str, TrainingJob] = {}


def _register_live(job: TrainingJob) -> None:
    with _LIVE_LOCK:
        _LIVE.add(job)


def _unregister_live(job: TrainingJob) -> None:
    with _LIVE_LOCK:
        _LIVE.discard(job)


@atexit.register
def stop_all_jobs(timeout: float = 20.0) -> None:
    """Stop every running trainer (SIGTERM, then kill): no orphan keeps a GPU busy."""
    with _LIVE_LOCK:
        live = list(_LIVE)
    for job in live:
        process = job._process
        if process is not None and process.poll() is None:
            job._cancel_requested = True
            _terminate(process, timeout)


def start_job(key: str, job: TrainingJob, *, resume: bool = False) -> TrainingJob:
    """Start ``job`` as the job of ``key`` (one per scene); refuses while one is running."""
    current = _JOBS.get(key)
    if current is not None and current.running:
        raise ESGSError(f"a training job is already running for {key!r}",
                        hint="cancel it or wait until it finishes")
    _JOBS[key] = job
    return job.start(resume=resume)


def get_job(key: str) -> Optional[TrainingJob]:
    """The latest job started for ``key`` (running or ended), or None."""
    return _JOBS.get(key)


def forget_job(key: str) -> None:
    """Drop an ended job from the registry (a running one is kept)."""
    job = _JOBS.get(key)
    if job is not None and not job.running:
        del _JOBS[key]
