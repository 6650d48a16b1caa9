"""The Blender-child line protocol: a child printing with print_event/print_error, and
run_child relaying its events and raising its errors in the parent."""
from __future__ import annotations

import sys
import textwrap

import pytest

from esgs.core.blender_child import report_error, run_child
from esgs.core.errors import ConfigError, DatasetError, ESGSError

# a stand-in for a Blender child: mixes log lines with protocol lines, then exits as asked
CHILD = textwrap.dedent("""
    import sys
    from esgs.core.blender_child import print_error, print_event
    from esgs.core.errors import {error_type}
    from esgs.core.progress import ProgressEvent

    print("Blender 5.0 log line", flush=True)
    for step in range(1, 4):
        print_event(ProgressEvent(step, 3, "render", metrics={{"psnr": 20.0 + step}}, message=f"view {{step}}"))
    if "{error_type}" != "ESGSError" or {status} == 2:
        print_error({error_type}("no cameras in sparse/0"))
    sys.exit({status})
""")


def child_command(error_type: str = "ESGSError", status: int = 0) -> list[str]:
    return [sys.executable, "-c", CHILD.format(error_type=error_type, status=status)]


def test_events_are_relayed_in_order_and_log_lines_hidden(capsys):
    events = []
    run_child(child_command(), events.append)
    assert [(event.step, event.total, event.stage, event.message) for event in events] == [
        (1, 3, "render", "view 1"), (2, 3, "render", "view 2"), (3, 3, "render", "view 3")]
    assert [event.metrics["psnr"] for event in events] == [21.0, 22.0, 23.0]
    assert "Blender 5.0 log line" not in capsys.readouterr().err


def test_verbose_shows_the_child_log_but_not_protocol_lines(capsys):
    run_child(child_command(), lambda event: None, verbose=True)
    err = capsys.readouterr().err
    assert "Blender 5.0 log line" in err and "ESGS_EVENT" not in err


@pytest.mark.parametrize("error_type, expected", [("ConfigError", ConfigError), ("DatasetError", DatasetError),
                                                  ("ESGSError", ESGSError)])
def test_child_error_is_raised_as_the_same_type(error_type, expected):
    events = []
    with pytest.raises(expected, match="no cameras in sparse/0") as raised:
        run_child(child_command(error_type, status=2), events.append, task="scene generation")
    assert type(raised.value) is expected
    assert len(events) == 3  # events before the error still reach the callback


def test_child_dying_without_an_error_line_names_task_and_status():
    with pytest.raises(ESGSError, match=r"label rendering failed \(exit status 3\)") as raised:
        run_child(child_command(status=3), lambda event: None, task="label rendering")
    assert "--verbose" in str(raised.value)


def test_report_error_goes_to_the_parent_or_to_the_console(capsys):
    assert report_error(ConfigError("bad preset"), program="make_scene", events_stdout=False) == 2
    captured = capsys.readouterr()
    assert captured.err.strip() == "make_scene: error: bad preset" and captured.out == ""
    assert report_error(DatasetError("no images"), program="make_scene", events_stdout=True) == 2
    line = capsys.readouterr().out
    assert line.startswith("ESGS_ERROR ") and '"type": "DatasetError"' in line and "no images" in line
