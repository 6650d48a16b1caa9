"""``esgs priors --events`` (what Blender's job runner follows) and the SfM writer's all-or-nothing output."""
from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from esgs.core.cli import main
from esgs.core.colmap import read_model
from esgs.core.priors import load_prior_maps
from esgs.core.priors import sfm
from esgs.core.priors.sfm import write_sfm_priors
from tests.blender.colmap_helpers import synthetic_model, write_scene


@pytest.fixture
def scene(tmp_path):
    return write_scene(tmp_path, synthetic_model())


def _events(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_events_file_follows_the_sfm_priors_and_ends_with_done(scene, tmp_path, capsys):
    events = tmp_path / "events.jsonl"
    assert main(["priors", str(scene), "--method", "sfm", "--events", str(events)]) == 0
    lines = _events(events)
    progress = [e for e in lines if e["kind"] == "progress"]
    assert [e["step"] for e in progress] == list(range(1, 9)) and {e["total"] for e in progress} == {8}
    assert lines[-1]["kind"] == "done" and lines[-1]["step"] == lines[-1]["total"] == 8
    assert "wrote sfm priors for 8 views" in lines[-1]["message"]
    # the maps are the projected points: the written depth equals sparse_depth_map's
    model = read_model(scene)
    image = model.sorted_images()[0]
    maps = load_prior_maps(scene, "sfm", image.name)
    np.testing.assert_array_equal(maps.depth, sfm.sparse_depth_map(model, image.image_id))
    assert maps.mask.sum() == np.count_nonzero(maps.depth) > 0


def test_an_error_is_an_error_event_and_exit_code_1(tmp_path, capsys):
    events = tmp_path / "events.jsonl"
    assert main(["priors", str(tmp_path / "missing"), "--method", "sfm", "--events", str(events)]) == 1  # bad data
    (line,) = _events(events)
    assert line["kind"] == "error" and "COLMAP model folder does not exist" in line["message"]
    assert not (tmp_path / "missing").exists()


def test_a_failed_sfm_run_keeps_the_previous_priors(scene, monkeypatch):
    model = read_model(scene)
    write_sfm_priors(scene, model)
    before = {p.relative_to(scene): p.read_bytes() for p in (scene / "priors").rglob("*") if p.is_file()}
    assert len(before) == 16  # depth + mask for 8 views
    calls = []
    original = sfm.sparse_depth_map

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 5:
            raise RuntimeError("disk full")
        return 2 * original(*args, **kwargs)  # different maps: a partial overwrite would show

    monkeypatch.setattr(sfm, "sparse_depth_map", failing)
    with pytest.raises(RuntimeError, match="disk full"):
        write_sfm_priors(scene, model)
    after = {p.relative_to(scene): p.read_bytes() for p in (scene / "priors").rglob("*") if p.is_file()}
    assert after == before
    assert [p.name for p in (scene / "priors").iterdir()] == ["sfm"]  # no staging folder left


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_sigterm_becomes_an_interrupt_so_the_writers_clean_up(scene, monkeypatch):
    """A cancel (SIGTERM) arriving while the maps are written leaves the previous priors."""
    import os
    import signal

    from esgs.core.commands.priors import _sigterm_interrupts

    model = read_model(scene)
    write_sfm_priors(scene, model)
    before = {p.relative_to(scene): p.read_bytes() for p in (scene / "priors").rglob("*") if p.is_file()}
    original, calls = sfm.sparse_depth_map, []

    def cancelled_midway(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGTERM)  # what TrainingJob.cancel sends
        return 2 * original(*args, **kwargs)

    monkeypatch.setattr(sfm, "sparse_depth_map", cancelled_midway)
    previous = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        with _sigterm_interrupts():
            write_sfm_priors(scene, model)
    assert signal.getsignal(signal.SIGTERM) is previous
    assert len(calls) == 3
    after = {p.relative_to(scene): p.read_bytes() for p in (scene / "priors").rglob("*") if p.is_file()}
    assert after == before and [p.name for p in (scene / "priors").iterdir()] == ["sfm"]
