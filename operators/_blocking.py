"""The frame shared by operators whose work is one blocking call (generate, render, label):
Blender's progress indicator around the call, our errors reported instead of raised, the
indicator closed whatever happens. Headless (``blender -b``, the bpy module) it blocks the
same way; the progress messages then go to the console.

Operators that start a background job (training, priors) block only when Blender runs
headless; :func:`finish_headless_job` is the end they share on that path."""
from __future__ import annotations

from typing import Any, Callable, Optional

import bpy

from ..core.apps import jobs
from ..core.errors import ESGSError
from ..core.apps.jobs import JobState
from ..core.progress import ProgressCallback, ProgressEvent


def blender_progress(context: bpy.types.Context) -> tuple[ProgressCallback, Any]:
    """A progress callback driving Blender's progress indicator and printing messages, and the
    window manager it drives (None where the context has none)."""
    window_manager = getattr(context, "window_manager", None)

    def report(event: ProgressEvent) -> None:
        if event.message:
            print(f"ESGS {event.stage}: {event.message}", flush=True)
        if window_manager is not None and event.total:
            window_manager.progress_update(int(100 * event.step / event.total))

    return report, window_manager


class BlockingJobOperator:
    """Mixin for a ``bpy.types.Operator`` (list it first among the bases): ``execute`` runs
    :meth:`run_job` under the progress indicator; an ESGSError becomes an ERROR report and
    ``CANCELLED``, success an INFO report of the returned sentence and ``FINISHED``."""

    # no class annotations here: Blender reads those of an operator class as its properties

    def run_job(self, context: bpy.types.Context, progress: ProgressCallback) -> str:
        """Do the work, reporting to ``progress``; return the sentence to show on success."""
        raise NotImplementedError

    def execute(self, context: bpy.types.Context) -> set[str]:
        progress, window_manager = blender_progress(context)
        if window_manager is not None:
            window_manager.progress_begin(0, 100)
        try:
            message = self.run_job(context, progress)
        except ESGSError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        finally:
            if window_manager is not None:
                window_manager.progress_end()
        self.report({"INFO"}, message)
        return {"FINISHED"}


def finish_headless_job(operator: Any, job: Any, settings: Any, *,
                        wait: Callable[[Any], JobState], copy_state: Callable[[Any, JobState], None],
                        name: str, success_message: Callable[[JobState], str],
                        after_success: Optional[Callable[[JobState], None]] = None,
                        after_success_failure: str = "") -> set[str]:
    """Follow a background job to its end where timers never fire (``blender -b``, the bpy module).

    Blocks in ``wait(job)`` (console progress), mirrors the final state into ``settings`` with
    ``copy_state(settings, state)``, then reports on ``operator``:

    - the job did not finish: ERROR ``"<name> <status>: <error or 'see the console'>"``, ``CANCELLED``;
    - it finished: ``after_success(state)`` runs (e.g. importing the result); an ESGSError from
      it is reported as ``"<after_success_failure>: <error>"`` with ``CANCELLED`` (other
      exceptions propagate: they are bugs, not user errors);
    - otherwise INFO ``success_message(state)`` and ``FINISHED``.

    Returns the operator's result set.
    """
    state = wait(job)
    copy_state(settings, state)
    if state.status != jobs.FINISHED:
        operator.report({"ERROR"}, f"{name} {state.status}: {state.error or 'see the console'}")
        return {"CANCELLED"}
    if after_success is not None:
        try:
            after_success(state)
        except ESGSError as error:
            prefix = after_success_failure or f"{name} finished but the step after it failed"
            operator.report({"ERROR"}, f"{prefix}: {error}")
            return {"CANCELLED"}
    operator.report({"INFO"}, success_message(state))
    return {"FINISHED"}
