"""The child-process runtime (core/runtime): config files, typed errors, stop-file cancel."""
from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from esgs.core.apps import jobs
from esgs.core.config import config_from_dict
from esgs.core.errors import ConfigError, DatasetError
from esgs.core.runtime import ChildJob, error_from_dict, error_to_dict, run_job
from esgs.core.runtime.child import read_config_data


def test_the_config_file_round_trips_the_settings_dataclass(tmp_path):
    from esgs.core.priors.job import PriorsSettings

    settings = PriorsSettings(scene=tmp_path / "scene", method="ndn", weights=tmp_path / "w.pt", steps=7, seed=3)
    job = ChildJob("priors", settings, workdir=tmp_path / "job", command=["unused"])
    job.workdir.mkdir()
    job.config_path.write_text(json.dumps(job.config_for_child()))
    assert config_from_dict(PriorsSettings, read_config_data(job.config_path)) == settings


def test_errors_keep_type_message_path_and_hint():
    error = DatasetError("no images", path="/scene", hint="render it first")
    again = error_from_dict(json.loads(json.dumps(error_to_dict(error))))
    assert type(again) is DatasetError and str(again) == str(error)
    assert (again.message, again.path, again.hint) == ("no images", Path("/scene"), "render it first")


def test_a_childs_config_error_comes_back_as_config_error_with_its_path(tmp_path):
    with pytest.raises(ConfigError, match="unknown setting") as raised:
        run_job("priors", {"scene": str(tmp_path), "method": "sfm", "bogus": 1}, workdir=tmp_path / "job")
    assert type(raised.value) is ConfigError
    assert raised.value.path == tmp_path / "job" / "job_config.json"  # the child's config file
    assert "known:" in raised.value.hint


def test_a_childs_dataset_error_comes_back_as_dataset_error(tmp_path):
    with pytest.raises(DatasetError) as raised:
        run_job("priors", {"scene": str(tmp_path / "missing"), "method": "sfm"})
    assert type(raised.value) is DatasetError and raised.value.path is not None


def test_a_relative_path_in_a_jobs_config_means_the_callers_folder(tmp_path, monkeypatch):
    """The child runs where the caller runs: ``esgs scene --out rover`` typed in a folder wrote
    to /tmp/rover when the child's working directory was its temporary work folder's parent."""
    pytest.importorskip("torch")
    from tests.core.train.scene import make_scene

    make_scene(tmp_path / "scene", views=3, width=16, height=12)
    monkeypatch.chdir(tmp_path)
    run_job("priors", {"scene": "scene", "method": "sfm"})
    assert any((tmp_path / "scene" / "priors" / "sfm").rglob("*.exr"))


def test_unknown_jobs_fail_in_the_parent(tmp_path):
    with pytest.raises(ConfigError, match="unknown child job"):
        ChildJob("no_such_job", {}, workdir=tmp_path)


def test_a_stop_file_stops_a_real_training_child_with_a_checkpoint(tmp_path):
    pytest.importorskip("torch")
    from tests.core.train.scene import make_scene

    scene = make_scene(tmp_path / "scene", views=4, width=16, height=12)
    run = tmp_path / "run"
    job = jobs.TrainingJob(scene, run, iterations=100_000, threads=1,
                           config={"progress_every": 1, "checkpoint_every": 0, "evaluate": False})
    job.start()
    deadline = time.monotonic() + 240
    while job.state().step < 3 and job.state().active and time.monotonic() < deadline:
        time.sleep(0.1)
    assert job.state().step >= 3, (job.state(), list(job.output_tail)[-5:])
    state = job.cancel(timeout=120)
    assert state.status == jobs.CANCELLED, state
    assert state.returncode == 0  # it stopped on the stop file, not on a signal
    assert job.result["status"] == "interrupted" and 3 <= job.result["step"] < 100_000
    assert sorted((run / "checkpoints").iterdir())  # the trainer saved where it stopped
    saved = json.loads((run / "config.json").read_text())
    assert saved["iterations"] == 100_000 and saved["progress_every"] == 1
