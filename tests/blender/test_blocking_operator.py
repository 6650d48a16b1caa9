"""The shared frame of blocking operators (operators/_blocking.py): the result, the reports,
and Blender's progress indicator opened, driven and closed on success and on failure; the
headless end of background jobs (finish_headless_job) on its three branches."""
from __future__ import annotations

from types import SimpleNamespace

import bpy
import pytest

from esgs.core.apps import jobs
from esgs.core.errors import ConfigError
from esgs.core.apps.jobs import JobState
from esgs.core.progress import ProgressEvent
from esgs.operators._blocking import BlockingJobOperator, finish_headless_job


class RecordingWindowManager:
    def __init__(self):
        self.calls: list[tuple] = []

    def progress_begin(self, low, high):
        self.calls.append(("begin", low, high))

    def progress_update(self, value):
        self.calls.append(("update", value))

    def progress_end(self):
        self.calls.append(("end",))


class Job(BlockingJobOperator):
    """The mixin without Blender's operator machinery: reports are recorded."""

    def __init__(self, fail: str = ""):
        self.fail = fail
        self.reports: list[tuple[set[str], str]] = []

    def report(self, kind, message):
        self.reports.append((kind, message))

    def run_job(self, context, progress):
        progress(ProgressEvent(1, 4, "test", message="a quarter"))
        if self.fail == "config":
            raise ConfigError("no folder chosen")
        if self.fail == "bug":
            raise ZeroDivisionError("a bug is not a user error")
        return "all done"


def test_success_reports_info_and_closes_the_indicator(capfd):
    window_manager = RecordingWindowManager()
    job = Job()
    assert job.execute(SimpleNamespace(window_manager=window_manager)) == {"FINISHED"}
    assert window_manager.calls == [("begin", 0, 100), ("update", 25), ("end",)]
    assert job.reports == [({"INFO"}, "all done")]
    assert "ESGS test: a quarter" in capfd.readouterr().out


def test_our_error_is_reported_and_the_indicator_closed():
    window_manager = RecordingWindowManager()
    job = Job("config")
    assert job.execute(SimpleNamespace(window_manager=window_manager)) == {"CANCELLED"}
    assert window_manager.calls[-1] == ("end",)
    assert job.reports == [({"ERROR"}, "no folder chosen")]


def test_other_exceptions_propagate_after_closing_the_indicator():
    window_manager = RecordingWindowManager()
    with pytest.raises(ZeroDivisionError):
        Job("bug").execute(SimpleNamespace(window_manager=window_manager))
    assert window_manager.calls[-1] == ("end",)


def test_works_without_a_window_manager():
    assert Job().execute(SimpleNamespace()) == {"FINISHED"}


class ESGS_OT_test_blocking_job(BlockingJobOperator, bpy.types.Operator):
    bl_idname = "esgs.test_blocking_job"
    bl_label = "Test Blocking Job"

    fail: bpy.props.BoolProperty(default=False)

    def run_job(self, context, progress):
        if self.fail:
            raise ConfigError("no folder chosen")
        return "all done"


def test_as_a_registered_operator():
    bpy.utils.register_class(ESGS_OT_test_blocking_job)
    try:
        assert bpy.ops.esgs.test_blocking_job() == {"FINISHED"}
        # bpy.ops turns the ERROR report of a cancelled operator into RuntimeError with its text
        with pytest.raises(RuntimeError, match="no folder chosen"):
            bpy.ops.esgs.test_blocking_job(fail=True)
    finally:
        bpy.utils.unregister_class(ESGS_OT_test_blocking_job)


# --------------------------------------------------------------------------- finish_headless_job


class Reporter:
    def __init__(self):
        self.reports: list[tuple[set[str], str]] = []

    def report(self, kind, message):
        self.reports.append((kind, message))


def finish(state: JobState, **kwargs):
    """Run finish_headless_job on a job whose wait returns ``state``; settings record the copy."""
    operator, settings, waited = Reporter(), SimpleNamespace(copied=None), []

    def wait(job):
        waited.append(job)
        return state

    def copy_state(target, final):
        target.copied = final

    result = finish_headless_job(operator, "the job", settings, wait=wait, copy_state=copy_state, name="Work",
                                 success_message=lambda final: f"did {final.total} things", **kwargs)
    assert waited == ["the job"]
    assert settings.copied is state  # the final state reaches the settings on every branch
    return result, operator.reports


def test_headless_job_success_reports_the_message():
    after = []
    result, reports = finish(JobState(status=jobs.FINISHED, step=7, total=7), after_success=after.append)
    assert result == {"FINISHED"}
    assert reports == [({"INFO"}, "did 7 things")]
    assert [state.total for state in after] == [7]


@pytest.mark.parametrize("status, error, shown", [
    (jobs.FAILED, "out of memory", "Work failed: out of memory"),
    (jobs.CANCELLED, "", "Work cancelled: see the console"),
])
def test_headless_job_that_did_not_finish_is_an_error(status, error, shown):
    after = []
    result, reports = finish(JobState(status=status, error=error), after_success=after.append)
    assert result == {"CANCELLED"}
    assert reports == [({"ERROR"}, shown)]
    assert after == []  # nothing is imported from a run that did not finish


def test_headless_job_whose_after_step_fails_is_an_error():
    def broken_import(state):
        raise ConfigError("the PLY has no vertices")

    result, reports = finish(JobState(status=jobs.FINISHED), after_success=broken_import,
                             after_success_failure="Work finished but importing failed")
    assert result == {"CANCELLED"}
    assert reports == [({"ERROR"}, "Work finished but importing failed: the PLY has no vertices")]
