"""The frame shared by operators whose work is one blocking call (generate, render, label):
Blender's progress indicator around the call, our errors reported instead of raised, the
indicator closed whatever happens. Headless (``blender -b``, the bpy module) it blocks the
same way; the progress messages then go to the console."""
from __future__ import annotations

from typing import Any

import bpy

from ..core.errors import ESGSError
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
