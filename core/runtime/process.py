"""The parent side of the runtime: start a registered job in a child process and follow it.

:class:`ChildJob` writes the job's config file (from its settings dataclass), starts
``python -m esgs.core.runtime.child JOB CONFIG --events E --result R --stop-file S`` in a
new process group/session, tails the JSON-lines events on a reader thread into a
:class:`JobState`, and at the end reads the child's result or error
(:func:`esgs.core.runtime.child.error_from_dict`). :meth:`ChildJob.cancel` writes the stop
file, which works on every platform (the trainer checkpoints on it), and only after a
timeout terminates, then kills, the child.

:func:`run_job` is the blocking form for jobs inside other jobs (the Blender scene render of
``esgs scene``, the label renderer, the demo's and bench's stages): progress relayed to a
callback, the child's error raised here as the same type, its result returned.

Plain Python, no bpy: the Blender operators and headless scripts both use it.
"""
from __future__ import annotations

import atexit
import collections
import dataclasses
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from ..config import config_to_dict
from ..errors import ConfigError, ESGSError
from ..io_utils import atomic_write_json
from ..progress import ProgressCallback, ProgressEvent, no_progress
from . import entry_points
from .child import EXIT_CANCELLED, error_from_dict

#: Status values of a job, in the order a job passes through them.
PENDING, RUNNING, FINISHED, FAILED, CANCELLED = "pending", "running", "finished", "failed", "cancelled"
ACTIVE_STATUSES = (PENDING, RUNNING)

_PACKAGE_ROOT = Path(__file__).resolve().parents[2]

#: the file names of one job's exchange folder (besides the events file, which may live elsewhere)
CONFIG_NAME, RESULT_NAME, STOP_NAME = "job_config.json", "job_result.json", "job_stop"
#: the events file's name when it lives in the exchange folder (a training job's lives in its run
#: folder, RunDir.events: the same name, but this folder is its own layout and the runtime sits
#: below the training layer)
EVENTS_NAME = "events.jsonl"


@dataclasses.dataclass
class JobState:
    """A snapshot of a job, safe to read from any thread (the job hands out copies).

    ``step``/``total`` come from the latest progress event; ``loss``, ``psnr``,
    ``n_gaussians`` and ``eta_s`` from its metrics (None until the child reports them).
    ``psnr_held_out``: the PSNR came from evaluation on held-out views (an ``eval`` stage or the
    final ``done`` event), not from the training views.
    ``error`` is set when ``status`` is ``"failed"``: the child's error message, or the
    last lines it printed.
    """

    status: str = PENDING
    step: int = 0
    total: int = 0
    stage: str = ""
    loss: Optional[float] = None
    psnr: Optional[float] = None
    psnr_held_out: bool = False
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

    def summary(self, psnr_parts: Optional[list[str]] = None) -> str:
        """One line for a status bar or a console: ``step 120/500 loss 0.0312 ...``.

        ``psnr_parts``: what to show in place of the PSNR (a caller with the run's own figures,
        e.g. the add-on's held-out metrics); None: this state's PSNR under its label."""
        parts = [self.status]
        if self.total:
            parts.append(f"step {self.step}/{self.total}")
        if self.loss is not None:
            parts.append(f"loss {self.loss:.4g}")
        if psnr_parts is not None:
            parts.extend(psnr_parts)
        elif self.psnr is not None:
            parts.append(f"{'held-out' if self.psnr_held_out else 'training'} PSNR {self.psnr:.2f} dB")
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
    """The Python interpreter that runs torch jobs (training, priors).

    Blender's own ``sys.executable`` has no torch, so the search is: ``preferred`` (the
    add-on preference) when set, ``$ESGS_PYTHON``, the project's virtual environment
    ``<package root>/.venv`` (a development checkout linked into Blender), then the
    running interpreter. The child then fails with an import error that the job reports.

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


def child_command(python: str | None = None) -> list[str]:
    """The command prefix of every child: ``[python, -m, esgs.core.runtime.child]``."""
    return [python or find_python(), "-m", entry_points.CHILD_MODULE]


def child_environment(extra: Optional[dict[str, str]] = None, threads: int = 0) -> dict[str, str]:
    """The environment of a child: ours, ``extra``, unbuffered output, thread counts, and
    the package's parent folder on ``PYTHONPATH`` for an installed extension."""
    env = dict(os.environ)
    env.update(extra or {})
    env["PYTHONUNBUFFERED"] = "1"
    # idle OpenMP threads spin by default; on a busy 2-core machine that tripled the CPU time
    # of torch + Numba steps (benchmarks/bench_rasterizer.py). Set for the child only: the
    # parent may be Blender, whose own threads are not ours to change
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if threads > 0:
        for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "ESGS_THREADS"):
            env[name] = str(threads)
    # An installed extension lives in a folder named after its id ("esgs"): putting its
    # parent on the path lets the child import the very same engine.
    if _PACKAGE_ROOT.name == entry_points.PACKAGE:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(_PACKAGE_ROOT.parent), env.get("PYTHONPATH")) if p)
    # Blender sets PYTHONHOME for its bundled Python; another interpreter must not inherit it.
    env.pop("PYTHONHOME", None)
    return env


def config_data(config: Any) -> dict[str, Any]:
    """The JSON object written as a job's config file: a settings dataclass through
    :func:`esgs.core.config.config_to_dict`, or a dict whose dataclass values are converted."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        return config_to_dict(config)
    if isinstance(config, dict):
        return {str(key): config_to_dict(value) for key, value in config.items()}
    raise ConfigError(f"a job config must be a settings dataclass or a dict, got {type(config).__name__}")


# --------------------------------------------------------------------------- the job


class ChildJob:
    """One registered job (:data:`esgs.core.runtime.entry_points.ENTRY_POINTS`) in a child process.

    Args:
        job: the job name (``"train"``, ``"priors"``, ``"scene"``...).
        config: the job's settings: a dataclass (or a dict of plain values and dataclasses),
            written as ``<workdir>/job_config.json`` when the job starts.
        workdir: the folder of the exchange files (config, result, stop file).
        events_path: the JSON-lines progress file (default ``<workdir>/events.jsonl``).
        command: the command prefix (default :func:`child_command`); tests pass a fake
            child script with the same interface.
        python: interpreter for the default command (see :func:`find_python`).
        threads: CPU threads for the child (``OMP_NUM_THREADS`` and friends); 0 keeps the default.
        on_output: called with every line the child prints (stdout and stderr merged),
            e.g. ``print`` for a headless run; called from the reader thread.
        on_event: called with every progress event, from the watcher thread.
        env: extra environment variables for the child.
    """

    #: what the job is called in messages ("training", "scene generation")
    task = "child process"

    def __init__(self, job: str, config: Any, *, workdir: str | os.PathLike,
                 events_path: str | os.PathLike | None = None, command: Sequence[str] | None = None,
                 python: str | None = None, threads: int = 0, on_output: Optional[Callable[[str], None]] = None,
                 on_event: Optional[ProgressCallback] = None, env: Optional[dict[str, str]] = None,
                 cwd: str | os.PathLike | None = None):
        entry_points.entry_point(job)  # an unknown job fails here, not in the child
        self.job = job
        self.config = config
        self.workdir = Path(workdir)
        self.events_path = Path(events_path) if events_path else self.workdir / EVENTS_NAME
        self.trainer = list(command) if command else child_command(python)
        self.threads = int(threads)
        self.on_output = on_output
        self.on_event = on_event
        self.env = dict(env or {})
        #: the child's working directory (relative paths in ``config`` resolve there); default
        #: the work folder's parent
        self.cwd = Path(cwd) if cwd is not None else self.workdir.parent
        self.output_tail: collections.deque[str] = collections.deque(maxlen=200)
        #: the child's return value once it finished; its handled error (same type) once it failed
        self.result: Any = None
        self.error: Optional[ESGSError] = None
        self._state = JobState()
        self._lock = threading.Lock()
        self._process: Optional[subprocess.Popen] = None
        self._threads: list[threading.Thread] = []
        self._finished = threading.Event()
        self._finished.set()  # nothing running yet: wait() returns at once
        self._cancel_requested = False
        self._done_event_seen = False
        self._error_event_message = ""

    # -- exchange files -------------------------------------------------------------

    @property
    def config_path(self) -> Path:
        return self.workdir / CONFIG_NAME

    @property
    def result_path(self) -> Path:
        return self.workdir / RESULT_NAME

    @property
    def stop_path(self) -> Path:
        return self.workdir / STOP_NAME

    def config_for_child(self, resume: bool = False) -> dict[str, Any]:
        """The JSON object the child reads (subclasses add run-specific values)."""
        return config_data(self.config)

    def command(self, resume: bool = False) -> list[str]:
        """The full command line the child runs."""
        return self.trainer + [self.job, str(self.config_path), "--events", str(self.events_path),
                               "--result", str(self.result_path), "--stop-file", str(self.stop_path)]

    def initial_total(self) -> int:
        """The progress total shown before the first event."""
        return 0

    def stopped_early(self) -> bool:
        """Whether the child's result says it stopped on request before its end (subclasses
        whose job reports that in its result override this; the trainer's "interrupted")."""
        return False

    def check(self) -> None:
        """Fail before starting for what would make the child fail (subclasses override)."""

    # -- public API ---------------------------------------------------------------

    def start(self, resume: bool = False) -> "ChildJob":
        """Write the config file and start the child; returns at once.

        Raises:
            ESGSError: the job is already running, or the child could not start.
        """
        with self._lock:
            if self._state.active and self._process is not None:
                raise ESGSError(f"this {self.task} job is already running", path=self.workdir,
                                hint="cancel it first or wait for it to finish")
        self.check()
        data = self.config_for_child(resume)
        with self._lock:
            self._state = JobState(status=RUNNING, total=self.initial_total(), started_at=time.time())
            self._cancel_requested = False
            self._done_event_seen = False
            self._error_event_message = ""
            self.result, self.error = None, None
            self.output_tail.clear()
            self._finished.clear()
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.events_path.parent.mkdir(parents=True, exist_ok=True)
        for stale in (self.stop_path, self.result_path):
            stale.unlink(missing_ok=True)
        atomic_write_json(self.config_path, data)
        # Events of earlier runs (a resumed trainer appends) are skipped by starting at the end.
        start_offset = self.events_path.stat().st_size if self.events_path.exists() else 0
        # A new session (process group on Windows) keeps a Ctrl-C in Blender's console or a
        # terminal from killing the child mid-write; cancel() and the exit handler stop it cleanly.
        platform_options: dict[str, Any] = (
            {"creationflags": getattr(subprocess, "CREATE_NEW_PROCESS_GROUP", 0)} if os.name == "nt"
            else {"start_new_session": True})
        try:
            self._process = subprocess.Popen(
                self.command(resume), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                env=child_environment(self.env, self.threads), cwd=str(self.cwd), **platform_options)
        except OSError as err:
            self._finish(FAILED, error=f"could not start the {self.task} ({self.trainer[0]}): {err}")
            raise ESGSError(f"could not start the {self.task}: {err}", path=self.trainer[0],
                            hint="check the Python interpreter in the add-on preferences") from err
        _register_live(self)
        output_thread = threading.Thread(target=self._read_output, name="esgs-job-output", daemon=True)
        watcher = threading.Thread(target=self._watch, args=(start_offset,), name="esgs-job-events", daemon=True)
        self._threads = [output_thread, watcher]
        for thread in self._threads:
            thread.start()
        return self

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
        headless run can print progress. Ctrl-C or SIGTERM cancels the child (the trainer
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
            # a killed script must not leave the child running on its own
            self.cancel()
            raise
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
        return self.state()

    def cancel(self, timeout: float = 120.0, *, wait: bool = True) -> JobState:
        """Ask the child to stop (the stop file: the trainer saves a checkpoint); after
        ``timeout`` seconds terminate it, then kill it.

        With ``wait=False`` (a UI button) this returns at once; the status turns to
        ``"cancelled"`` when the child has exited.
        """
        process = self._process
        if process is None or process.poll() is not None:
            self._finished.wait(5.0)
            return self.state()
        self._cancel_requested = True
        if not wait:
            threading.Thread(target=stop_process, args=(process, self.stop_path, timeout), name="esgs-job-cancel",
                             daemon=True).start()
            return self.state()
        stop_process(process, self.stop_path, timeout)
        self._finished.wait(timeout)
        return self.state()

    # -- internals ----------------------------------------------------------------

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
        record = self._read_result()
        if record.get("status") == "error" and isinstance(record.get("error"), dict):
            self.error = error_from_dict(record["error"])
        self.result = record.get("result")
        stopped = record.get("status") == "cancelled" or returncode == EXIT_CANCELLED
        if self._cancel_requested and not self._done_event_seen or stopped or self.stopped_early():
            self._finish(CANCELLED, returncode=returncode)
        elif returncode == 0 and self.error is None and not self._error_event_message:
            self._finish(FINISHED, returncode=returncode)
        else:
            self._finish(FAILED, returncode=returncode, error=self._failure_message(returncode))

    def _read_result(self) -> dict[str, Any]:
        try:
            record = json.loads(self.result_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}
        return record if isinstance(record, dict) else {}

    def _failure_message(self, returncode: int) -> str:
        if self.error is not None:
            return str(self.error)
        if self._error_event_message:
            return self._error_event_message
        lines = [line for line in self.output_tail if line.strip()]
        # the last traceback line ("ModuleNotFoundError: No module named 'torch'") says what went wrong
        for line in reversed(lines):
            if "error" in line.lower() or "exception" in line.lower():
                if line.startswith("ModuleNotFoundError"):
                    # the usual cause: Blender's own Python, which has no torch
                    return (f"{line.strip()} (the {self.task} ran with {self.trainer[0]}; set a Python that has "
                            "torch and esgs in the add-on preferences or $ESGS_PYTHON)")
                return line.strip()
        if lines:
            return lines[-1].strip()
        return f"the {self.task} exited with code {returncode}"

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
                state.psnr_held_out = event.stage == "eval" or event.kind == "done"
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
                self._error_event_message = event.message or f"the {self.task} reported an error"
        if self.on_event is not None:
            try:
                self.on_event(event)
            except Exception:  # noqa: BLE001 - a display callback must not kill the watcher
                pass

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
    """SIGTERM received while blocking in :meth:`ChildJob.wait` (exit status 143)."""


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


def stop_process(process: subprocess.Popen, stop_file: Path, timeout: float) -> None:
    """Stop a child: write its stop file (every platform; the trainer checkpoints), wait up to
    ``timeout`` seconds, then terminate it (SIGTERM: the trainer checkpoints too), then kill it."""
    try:
        stop_file.parent.mkdir(parents=True, exist_ok=True)
        stop_file.write_text("stop requested by the parent process\n", encoding="utf-8")
    except OSError:
        pass  # an unwritable folder still leaves the signals below
    try:
        process.wait(timeout)
        return
    except subprocess.TimeoutExpired:
        pass
    try:
        process.terminate()
        process.wait(10.0)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(10.0)
    except (ProcessLookupError, OSError):
        pass


# --------------------------------------------------------------------------- blocking


def run_job(job: str, config: Any, progress: ProgressCallback = no_progress, *, task: str = "",
            verbose: bool = False, python: str | None = None, command: Sequence[str] | None = None,
            threads: int = 0, workdir: str | os.PathLike | None = None) -> Any:
    """Run ``job`` with ``config`` in a child process to its end and return its result.

    Progress events are relayed to ``progress``; the child's output is shown on stderr
    only with ``verbose``. ``python`` defaults to this interpreter (the Blender children need
    the bpy module it has). Ctrl-C stops the child through its stop file first.

    Raises:
        ESGSError: the child's handled error as the same type (ConfigError, DatasetError,
            CheckpointError...), or ESGSError naming ``task`` and the child's last output
            when it died without one.
    """
    label = task or f"{job} job"
    temporary = workdir is None
    folder = Path(tempfile.mkdtemp(prefix=f"esgs_{job}_")) if temporary else Path(workdir)
    echo = (lambda line: print(line, file=sys.stderr)) if verbose else None
    # the caller's working directory: a relative path in ``config`` (esgs scene --out rover) means
    # what it meant where the command was typed, not a folder beside the temporary work folder
    child = ChildJob(job, config, workdir=folder, command=command or child_command(python or sys.executable),
                     threads=threads, on_output=echo, on_event=progress, cwd=os.getcwd())
    child.task = label
    try:
        child.start()
        state = child.wait(poll_s=0.2)
    finally:
        if temporary and not child.running:
            import shutil

            shutil.rmtree(folder, ignore_errors=True)
    if state.status == FINISHED:
        return child.result
    if child.error is not None:
        raise child.error
    if state.status == CANCELLED:
        raise ESGSError(f"{label} was stopped before it finished")
    tail = " | ".join(line.strip() for line in list(child.output_tail)[-8:])
    raise ESGSError(f"{label} failed (exit status {state.returncode})" + (f": {tail}" if tail else ""),
                    hint="run again with --verbose to see the child's whole output")


# --------------------------------------------------------------------------- registry


_LIVE: set[ChildJob] = set()
_LIVE_LOCK = threading.Lock()
_JOBS: dict[str, ChildJob] = {}


def _register_live(job: ChildJob) -> None:
    with _LIVE_LOCK:
        _LIVE.add(job)


def _unregister_live(job: ChildJob) -> None:
    with _LIVE_LOCK:
        _LIVE.discard(job)


@atexit.register
def stop_all_jobs(timeout: float = 20.0) -> None:
    """Stop every running child (stop file, then terminate, then kill): no orphan keeps a GPU busy."""
    with _LIVE_LOCK:
        live = list(_LIVE)
    running = [(job, job._process) for job in live if job._process is not None and job._process.poll() is None]
    for job, process in running:
        job._cancel_requested = True
        threading.Thread(target=stop_process, args=(process, job.stop_path, timeout), daemon=True).start()
    for job, process in running:
        try:
            process.wait(timeout + 25.0)
        except subprocess.TimeoutExpired:
            pass


def start_job(key: str, job: ChildJob, *, resume: bool = False) -> ChildJob:
    """Start ``job`` as the job of ``key`` (one per scene); refuses while one is running."""
    current = _JOBS.get(key)
    if current is not None and current.running:
        raise ESGSError(f"a {current.task} job is already running for {key!r}",
                        hint="cancel it or wait until it finishes")
    _JOBS[key] = job
    return job.start(resume=resume)


def get_job(key: str) -> Optional[ChildJob]:
    """The latest job started for ``key`` (running or ended), or None."""
    return _JOBS.get(key)


def forget_job(key: str) -> None:
    """Drop an ended job from the registry (a running one is kept)."""
    job = _JOBS.get(key)
    if job is not None and not job.running:
        del _JOBS[key]
