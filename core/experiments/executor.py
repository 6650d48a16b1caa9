"""Run many independent tasks: a local process pool or a Ray cluster, same interface.

``run_tasks(tasks, function, executor)`` skips tasks that are already finished
(``task.finished()``), runs the rest through the executor, retries a failed task once and
returns one :class:`TaskOutcome` per task (failures are reported, never raised), so a
long experiment survives one bad run and a restart repeats only what did not finish.
"""
from __future__ import annotations

import traceback
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
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


class RayExecutor(Executor):
    """Tasks as Ray remote functions on the cluster at ``address`` ("auto" = a local one).

    Ray is optional: it is imported here only, with a clear error when it is missing.
    """

    def __init__(self, address: Optional[str] = None, num_cpus_per_task: float = 1.0,
                 num_gpus_per_task: float = 0.0):
        try:
            import ray
        except ImportError as err:
            raise ConfigError("the Ray executor needs the 'ray' package, which is not installed",
                              hint="pip install ray, or drop --address to use the local process pool") from err
        self.ray = ray
        if not ray.is_initialized():
            ray.init(address=address)
        self.remote = ray.remote(num_cpus=num_cpus_per_task, num_gpus=num_gpus_per_task)(_call)

    def submit(self, function: Callable[[Any], Any], task: Any) -> Future:
        return self.remote.remote(function, task).future()


def make_executor(kind: str = "local", *, max_workers: int = 1, address: Optional[str] = None) -> Executor:
    """"local" (process pool), "ray" (needs ray) or "auto" (Ray when an address is given)."""
    if kind == "auto":
        kind = "ray" if address else "local"
    if kind == "local":
        return LocalExecutor(max_workers)
    if kind == "ray":
        return RayExecutor(address)
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
