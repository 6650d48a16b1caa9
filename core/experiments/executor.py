"""Run many independent tasks: a local process pool or a Ray cluster, same interface.

``run_tasks(tasks, function, executor)`` skips tasks that are already finished
(``task.finished()``), runs the rest through the executor, retries a failed task once and
returns one :class:`TaskOutcome` per task (failures are reported, never raised), so a
long experiment survives one bad run and a restart repeats only what did not finish.
"""
from __future__ import annotations

import io
import math
import tarfile
import traceback
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from ..errors import ConfigError


@dataclass
class TaskOutcome:
    """What became of one task: ``status`` "done" | "skipped" | "failed"; ``attempts`` made."""

    task: Any
    status: str
    result: Any = None
    error: Optional[str] = None
    attempts: int = 0


def _call(function: Callable[[Any], Any], task: Any) -> tuple[bool, Any]:
    """Run in the worker: (True, result) or (False, error text) so failures cross processes as data."""
    try:
        return True, function(task)
    except BaseException as err:  # noqa: BLE001 - reported to the caller, who retries once
        return False, f"{type(err).__name__}: {err}\n{traceback.format_exc(limit=6)}"


class Executor:
    """Submits ``function(task)`` calls; subclasses decide where they run."""

    def submit(self, function: Callable[[Any], Any], task: Any) -> Future:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class LocalExecutor(Executor):
    """A pool of ``max_workers`` processes; each task gets a fresh process (spawned), so its
    peak memory (``ru_maxrss``) is its own and a crash cannot poison the next task."""

    def __init__(self, max_workers: int = 1):
        import multiprocessing

        if max_workers < 1:
            raise ConfigError(f"max_workers must be >= 1, got {max_workers}")
        self.pool = ProcessPoolExecutor(max_workers=max_workers, mp_context=multiprocessing.get_context("spawn"),
                                        max_tasks_per_child=1)

    def submit(self, function: Callable[[Any], Any], task: Any) -> Future:
        return self.pool.submit(_call, function, task)

    def close(self) -> None:
        self.pool.shutdown(wait=True)


#: Left behind on the worker when a run folder travels back: resumable state, not results.
SHIPPED_EXCLUDES = ("checkpoints",)


def pack_folder(folder: Path, exclude: Sequence[str] = SHIPPED_EXCLUDES) -> bytes:
    """``folder``'s files as an in-memory gzip tar (top-level names in ``exclude`` left out)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as archive:
        for child in sorted(Path(folder).iterdir()):
            if child.name not in exclude:
                archive.add(child, arcname=child.name)
    return buffer.getvalue()


def unpack_folder(data: bytes, folder: Path) -> Path:
    """Write an archive of :func:`pack_folder` to ``folder`` (built aside, then renamed into place)."""
    from ..io_utils import atomic_directory

    with atomic_directory(folder, overwrite=True) as tmp:
        with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as archive:
            archive.extractall(tmp, filter="data")  # "data": no absolute paths, links or devices
    return Path(folder)


#: Name prefix of the scratch folder a shipped run trains in.
SCRATCH_PREFIX = "esgs_run_"


def _run_shipped(function: Callable[[Any], Any], task: Any, scene_archive: Optional[bytes]) -> tuple[bool, Any, Any]:
    """Run ``task`` in a scratch folder of this node: the scene unpacked from ``scene_archive``,
    the run folder packed and returned so the driver can put it where the task says."""
    import dataclasses
    import tempfile

    with tempfile.TemporaryDirectory(prefix=SCRATCH_PREFIX) as scratch:
        changes: dict[str, Any] = {"out": Path(scratch) / "run"}
        if scene_archive is not None:
            # under its own name: the run's config.json names the scene it trained on (RunTask.stale_settings)
            scene = unpack_folder(scene_archive, Path(scratch) / "scene" / Path(task.scene).name)
            changes["scene"] = scene
            mesh = getattr(task, "mesh", None)
            if mesh is not None and Path(mesh).is_relative_to(task.scene):
                changes["mesh"] = scene / Path(mesh).relative_to(task.scene)
        local_task = dataclasses.replace(task, **changes)
        ok, value = _call(function, local_task)
        folder = changes["out"]
        archive = pack_folder(folder) if ok and folder.is_dir() else None
    return ok, value, archive


def _is_run_task(task: Any) -> bool:
    """True for dataclass tasks with ``out`` and ``scene`` folders (the experiments' run tasks)."""
    import dataclasses

    return dataclasses.is_dataclass(task) and hasattr(task, "out") and hasattr(task, "scene")


def _remote_call(function: Callable[[Any], Any], task: Any, driver_host: str, ship: str,
                 scene_archive: Optional[bytes]) -> tuple[bool, Any, Any]:
    """A Ray task. ``ship``: "never" (the node shares the driver's disk), "other_hosts" (run in
    place on the driver's host, in a scratch folder elsewhere) or "always" (scratch folder)."""
    import socket

    shipped = ship == "always" or (ship == "other_hosts" and socket.gethostname() != driver_host)
    if not shipped or not _is_run_task(task):
        ok, value = _call(function, task)
        return ok, value, None
    return _run_shipped(function, task, scene_archive)


class RayExecutor(Executor):
    """Tasks as Ray tasks: on a local Ray instance started here (``address=None``, nothing to set
    up; ``num_cpus`` defaults to this machine's cores) or on the cluster at ``address``.

    Each task runs in a fresh worker process (``max_calls=1``) so its peak memory is its own.
    Folders travel for clusters whose nodes do not share the driver's disk: with an
    ``address`` (``ship_folders=None``) a run on another host than the driver's gets its scene
    folder through Ray's object store (packed once per scene), trains in a scratch folder, and
    its run folder (without checkpoints) comes back to ``task.out`` on the driver, so
    summaries, renders and point clouds all land in one place. ``ship_folders=True`` does this
    for every run (tests; hosts sharing a name), ``False`` never (a shared file system).
    :meth:`close` shuts down a local instance started here and disconnects from a cluster
    connected here (the cluster keeps running); a Ray already initialised by the caller is left alone.
    """

    def __init__(self, address: Optional[str] = None, *, num_cpus: Optional[int] = None,
                 num_cpus_per_task: float = 1.0, num_gpus_per_task: float = 0.0, ship_folders: Optional[bool] = None,
                 object_store_mib: int = 256):
        import os
        import socket

        try:
            import ray
        except ImportError as err:
            raise ConfigError("the Ray executor needs the 'ray' package, which is not installed",
                              hint="pip install -r requirements.txt, or use --executor local") from err
        self.ray = ray
        self.started_here = False  # True: close() ends what this executor opened
        if not ray.is_initialized():
            self.started_here = True
            if address:
                try:
                    ray.init(address=address, log_to_driver=False)
                except ConnectionError as err:
                    # Ray >= 2.5x clusters use token authentication by default; drivers do not
                    raise ConfigError(f"cannot connect to the Ray cluster at {address}: {err}",
                                      hint="check `ray status --address ADDRESS`; with token authentication run "
                                           "with RAY_AUTH_MODE=token and the cluster's ~/.ray/auth_token") from err
            else:
                # a light local instance: no dashboard, a small object store (results are small dicts)
                # never fewer CPUs than one task reserves, or that task would wait forever
                cpus = max(num_cpus or os.cpu_count() or 1, math.ceil(num_cpus_per_task))
                # address="local": always a new instance, never a cluster that `ray start` left registered
                ray.init(address="local", num_cpus=cpus, include_dashboard=False, log_to_driver=False,
                         object_store_memory=object_store_mib * 1024 * 1024)
        if ship_folders is None:
            self.ship = "other_hosts" if address else "never"
        else:
            self.ship = "always" if ship_folders else "never"
        self.driver_host = socket.gethostname()
        self.scene_refs: dict[str, Any] = {}
        self.remote = ray.remote(num_cpus=num_cpus_per_task, num_gpus=num_gpus_per_task, max_calls=1,
                                 max_retries=0)(_remote_call)

    def _scene_ref(self, task: Any) -> Any:
        """The scene folder of ``task`` in the object store, packed once per scene (None: not shipped)."""
        if self.ship == "never" or not _is_run_task(task):
            return None
        key = str(Path(task.scene).resolve())
        if key not in self.scene_refs:
            self.scene_refs[key] = self.ray.put(pack_folder(Path(task.scene), exclude=()))
        return self.scene_refs[key]

    def submit(self, function: Callable[[Any], Any], task: Any) -> Future:
        outer: Future = Future()
        inner = self.remote.remote(function, task, self.driver_host, self.ship, self._scene_ref(task)).future()

        def finish(done: Future) -> None:
            try:
                ok, value, archive = done.result()
                if archive is not None:
                    unpack_folder(archive, Path(task.out))
                outer.set_result((ok, value))
            except BaseException as err:  # noqa: BLE001 - a lost worker or a bad archive: the task failed
                outer.set_exception(err)

        inner.add_done_callback(finish)
        return outer

    def close(self) -> None:
        self.scene_refs.clear()
        if self.started_here:
            self.ray.shutdown()
            self.started_here = False


def make_executor(kind: str = "local", *, max_workers: int = 0, address: Optional[str] = None,
                  cpus_per_task: float = 1.0) -> Executor:
    """"local" (process pool of ``max_workers``, default 1) or "ray" (a local Ray instance of
    ``max_workers`` CPUs, default all cores, or the cluster at ``address``); "auto" = Ray when
    an address is given."""
    if kind == "auto":
        kind = "ray" if address else "local"
    if kind == "local":
        return LocalExecutor(max_workers or 1)
    if kind == "ray":
        return RayExecutor(address, num_cpus=(int(max_workers * cpus_per_task) or None) if max_workers else None,
                           num_cpus_per_task=cpus_per_task)
    raise ConfigError(f"unknown executor {kind!r}", hint="use local, ray or auto")


def run_tasks(tasks: Sequence[Any], function: Callable[[Any], Any], executor: Executor, *,
              retries: int = 1, on_outcome: Optional[Callable[[TaskOutcome], None]] = None) -> list[TaskOutcome]:
    """Run every unfinished task; a failed one is submitted again up to ``retries`` times.

    ``function`` must be picklable (a module-level function). ``tasks`` with a
    ``finished()`` method returning True are skipped. Outcomes are in the order of ``tasks``.
    """
    outcomes: list[Optional[TaskOutcome]] = [None] * len(tasks)
    pending: dict[Future, int] = {}
    attempts = [0] * len(tasks)
    for index, task in enumerate(tasks):
        finished = getattr(task, "finished", None)
        if finished is not None and finished():
            outcomes[index] = TaskOutcome(task, "skipped", result=getattr(task, "load_summary", lambda: None)())
            if on_outcome:
                on_outcome(outcomes[index])
            continue
        attempts[index] = 1
        pending[executor.submit(function, task)] = index
    while pending:
        done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
        for future in done:
            index = pending.pop(future)
            try:
                ok, value = future.result()
            except BaseException as err:  # noqa: BLE001 - a dead worker process
                ok, value = False, f"{type(err).__name__}: {err}"
            if not ok and attempts[index] <= retries:
                attempts[index] += 1
                pending[executor.submit(function, tasks[index])] = index
                continue
            outcomes[index] = TaskOutcome(tasks[index], "done" if ok else "failed", result=value if ok else None,
                                          error=None if ok else value, attempts=attempts[index])
            if on_outcome:
                on_outcome(outcomes[index])
    return [outcome for outcome in outcomes if outcome is not None]
