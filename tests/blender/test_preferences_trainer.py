"""The trainer part of the preferences: the search order, the Set Up Trainer / Cancel / Check /
Remove operators (the headless blocking path and the background job's timer, called directly
since timers never fire headless), and what the preferences draw in each state."""
from __future__ import annotations

import sys
import sysconfig
import time
from pathlib import Path

import pytest

bpy = pytest.importorskip("bpy")

import esgs  # noqa: E402
from esgs.esgs_addon import preferences, trainer_setup  # noqa: E402
from esgs.esgs_addon.trainer_setup import SetupCommand  # noqa: E402
from esgs.operators import trainer_setup as setup_operators  # noqa: E402
from tests.blender.panel_drawing import draw_preferences  # noqa: E402


def labels(calls) -> list[str]:
    return [call.text for call in calls if call.name == "label"]


def operators(calls) -> list[str]:
    return [call.text for call in calls if call.name == "operator"]


#: set by ``isolated_trainer``: an installed extension's folder (``.../user_default/esgs``, a link to the checkout)
EXTENSION = Path()


@pytest.fixture(autouse=True)
def isolated_trainer(tmp_path, monkeypatch):
    """The set-up's folder in tmp_path; no $ESGS_PYTHON; no job or check lines from another test."""
    monkeypatch.delenv("ESGS_PYTHON", raising=False)
    monkeypatch.setattr(preferences, "environment_dir", lambda create=False: tmp_path / "user" / "trainer")
    monkeypatch.setitem(preferences.SETUP, "job", None)
    monkeypatch.setitem(preferences.SETUP, "check", [])
    preferences.forget_trainer_checks()
    (tmp_path / "extensions" / "user_default").mkdir(parents=True)
    extension = tmp_path / "extensions" / "user_default" / "esgs"
    extension.symlink_to(Path(esgs.__file__).parent, target_is_directory=True)
    monkeypatch.setattr(sys.modules[__name__], "EXTENSION", extension)
    yield tmp_path / "user" / "trainer"
    job = preferences.SETUP["job"]
    if job is not None:
        job.cancel()
        job.wait(10)


def fake_environment(folder: Path) -> Path:
    """A folder shaped like a venv whose bin/python is the suite's interpreter (which has torch)."""
    (folder / "bin").mkdir(parents=True)
    (folder / "bin" / "python").symlink_to(sys.executable)
    return folder / "bin" / "python"


def working_planner(folder: Path) -> list[SetupCommand]:
    """A real (pip-less) venv that sees the suite's site-packages through a .pth file, then the check."""
    python = str(trainer_setup.venv_python(folder))
    site = sysconfig.get_paths()["purelib"]
    return [SetupCommand("venv", "make", (sys.executable, "-m", "venv", "--without-pip", str(folder))),
            SetupCommand("requirements", "link", (python, "-c", "import sys, sysconfig; open(sysconfig.get_paths()"
                                                                "['purelib'] + '/suite.pth', 'w').write(sys.argv[1])",
                                                  site)),
            SetupCommand("engine", "engine", (python, "-c", trainer_setup._ENGINE_SCRIPT, str(EXTENSION))),
            SetupCommand("verify", "check", (python, "-c", trainer_setup.VERIFY_SCRIPT, "check", "numpy"))]


def slow_planner(folder: Path) -> list[SetupCommand]:
    return [SetupCommand("venv", "make", (sys.executable, "-c", "import os, sys; os.makedirs(sys.argv[1])", str(folder))),
            SetupCommand("torch", "Install torch", (sys.executable, "-c", "import time; print('Collecting torch', "
                                                                          "flush=True); time.sleep(60)"))]


def test_search_order(isolated_trainer, tmp_path, monkeypatch):
    python, source = preferences.trainer_choice()
    assert source in ("the checkout's .venv", "Blender's own Python")
    managed = fake_environment(isolated_trainer)
    assert preferences.trainer_choice() == (str(managed), "Set Up Trainer")
    other = fake_environment(tmp_path / "other")
    monkeypatch.setenv("ESGS_PYTHON", str(other))
    assert preferences.trainer_choice() == (str(other), "$ESGS_PYTHON")
    assert preferences.trainer_python() == str(other)


def test_a_trainer_without_torch_is_a_warning(tmp_path, monkeypatch):
    no_torch = tmp_path / "python"
    no_torch.write_text("#!/bin/sh\nexit 1\n")
    no_torch.chmod(0o755)
    monkeypatch.setenv("ESGS_PYTHON", str(no_torch))
    shown = labels(draw_preferences(esgs))
    assert f"Trainer runs with: {no_torch} ($ESGS_PYTHON)" in shown
    assert any("cannot import torch" in text for text in shown)
    monkeypatch.delenv("ESGS_PYTHON")
    shown = labels(draw_preferences(esgs))  # the suite's own Python has torch
    assert not any("cannot import torch" in text for text in shown)
    assert any(text.startswith("Not set up: ") for text in shown)


def test_set_up_headless_blocks_and_the_result_becomes_the_trainer(isolated_trainer, monkeypatch):
    monkeypatch.setattr(preferences, "setup_options", lambda context=None: {
        "python": sys.executable, "variant": "cpu", "planner": working_planner})
    assert bpy.app.background
    assert bpy.ops.esgs.trainer_setup() == {"FINISHED"}
    assert (isolated_trainer / "bin" / "python").is_file()
    assert preferences.trainer_choice()[1] == "Set Up Trainer"
    shown = labels(draw_preferences(esgs))
    assert any(text.startswith("Installed: ") for text in shown)
    assert any(text.startswith("torch 2.") for text in shown)  # the check's lines

    assert bpy.ops.esgs.trainer_check() == {"FINISHED"}
    assert preferences.SETUP["check"][0] == "Trainer from Set Up Trainer"
    assert bpy.ops.esgs.trainer_remove() == {"FINISHED"}
    assert not isolated_trainer.exists()
    assert preferences.trainer_choice()[1] != "Set Up Trainer"


def test_a_failed_set_up_headless_reports_and_keeps_nothing(isolated_trainer, monkeypatch):
    def failing(folder):
        return [SetupCommand("venv", "make", (sys.executable, "-c", "import os, sys; os.makedirs(sys.argv[1])",
                                              str(folder))),
                SetupCommand("torch", "Install torch", (sys.executable, "-c",
                                                        "print('ERROR: No matching distribution found for torch'); "
                                                        "raise SystemExit(1)"))]
    monkeypatch.setattr(preferences, "setup_options", lambda context=None: {"variant": "cpu", "planner": failing})
    with pytest.raises(RuntimeError, match="a package was not found"):
        bpy.ops.esgs.trainer_setup()
    assert not isolated_trainer.parent.exists() or not any(isolated_trainer.parent.iterdir())


def test_the_background_set_up_its_progress_cancel_and_end(isolated_trainer, monkeypatch):
    """The interactive path: the job on its thread, the timer callback called by hand."""
    job = trainer_setup.SetupJob(isolated_trainer, planner=slow_planner).start()
    preferences.SETUP["job"] = job
    deadline = time.monotonic() + 30
    while "Collecting torch" not in job.tail(3) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert setup_operators.poll_setup() == pytest.approx(0.5)  # still running: poll again
    drawn = draw_preferences(esgs)
    assert "esgs.trainer_setup_cancel" in operators(drawn) and "esgs.trainer_setup" not in operators(drawn)
    assert any(text.startswith("Setting up (") and "Install torch" in text for text in labels(drawn))
    assert "Collecting torch" in labels(drawn)  # the log

    assert bpy.ops.esgs.trainer_setup() == {"CANCELLED"}  # one at a time
    assert bpy.ops.esgs.trainer_setup_cancel() == {"FINISHED"}
    assert job.wait(15) and job.status == "cancelled"
    assert setup_operators.poll_setup() is None
    drawn = draw_preferences(esgs)
    assert "The set-up was cancelled; nothing was kept" in labels(drawn)
    assert "esgs.trainer_setup" in operators(drawn)
    assert not isolated_trainer.exists() and not any(isolated_trainer.parent.iterdir())


def test_automatic_variant_follows_the_gpu(monkeypatch):
    monkeypatch.setattr(trainer_setup.shutil, "which", lambda name: None)
    options = preferences.setup_options()
    assert options["variant"] == "cpu" and options["python"] == sys.executable
    assert options["find_links"] is None and options["index_url"] is None
    monkeypatch.setattr(trainer_setup.shutil, "which", lambda name: "/usr/bin/nvidia-smi" if name == "nvidia-smi" else None)
    if sys.platform != "darwin":
        assert preferences.setup_options()["variant"] == "cuda"
    assert any("Automatic: " in text for text in labels(draw_preferences(esgs)))
