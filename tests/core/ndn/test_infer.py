"""NDN end to end on tiny data: train with resume, evaluate, write priors/ndn for a scene."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from esgs.core.cli import main
from esgs.core.errors import CheckpointError
from esgs.core.ndn.config import NDNTrainConfig
from esgs.core.ndn.data import scene_triples, write_shard
from esgs.core.ndn.infer import evaluate_ndn, guided_upsample
from esgs.core.ndn.train import build_model, load_checkpoint, save_checkpoint, train_ndn
from esgs.core.priors import load_prior_maps
from esgs.core.progress import ProgressEvent

from .conftest import perturbed_weights, tiny_config


def _data(tmp_path, scene):
    triples = scene_triples(scene, 32, 2)
    write_shard(tmp_path / "data" / "shards" / "train_plane_1.npz", triples, {})
    write_shard(tmp_path / "data" / "shards" / "heldout_plane_100000.npz", triples, {})
    return tmp_path / "data"


def test_training_resumes_and_evaluation_scores(scene, tmp_path):
    data = _data(tmp_path, scene)
    events: list[ProgressEvent] = []
    settings = NDNTrainConfig(steps=2, batch_size=2, checkpoint_every=1, seed=0)
    summary = train_ndn(data, tmp_path / "model", settings, tiny_config(), progress=events.append)
    assert summary["steps"] == 2 and (tmp_path / "model/checkpoints/step_0000002.pt").exists()
    assert [e.step for e in events if e.kind == "progress"] == [1, 2]
    assert "loss" in events[0].metrics and np.isfinite(events[0].metrics["loss"])
    resumed = train_ndn(data, tmp_path / "model", NDNTrainConfig(steps=3, batch_size=2, checkpoint_every=1),
                        resume=True)
    assert resumed["resumed_from"] == 2 and resumed["steps"] == 3
    _, _, config, payload = load_checkpoint(tmp_path / "model")
    # trained with the default --monocular, so it reads panoramas one view at a time
    expected = tiny_config()
    expected = dataclasses.replace(expected, model=dataclasses.replace(expected.model, panorama_input="centre"))
    assert payload["step"] == 3 and config == expected
    scores = evaluate_ndn(tmp_path / "model", data, steps=2, limit=2)
    assert scores["views"] == 2
    assert 0 <= scores["abs_rel"] and 0 <= scores["delta1"] <= 1
    assert 0 <= scores["normal_mean_deg"] <= 180 and 0 <= scores["normal_within_11_25"] <= 1


def test_evaluation_reports_each_scene(scene, tmp_path):
    data = _data(tmp_path, scene)
    triples = scene_triples(scene, 32, 2)
    count = len(triples.names)
    write_shard(data / "shards" / "heldout_plane_100001.npz", triples, {})
    save_checkpoint(tmp_path / "model.pt", build_model(tiny_config())[0], tiny_config())
    scores = evaluate_ndn(tmp_path / "model.pt", data, steps=2)
    assert list(scores["per_scene"]) == ["heldout_plane_100000", "heldout_plane_100001"]
    assert [s["views"] for s in scores["per_scene"].values()] == [count, count] and scores["views"] == 2 * count
    for key in ("abs_rel", "delta1", "normal_mean_deg", "normal_within_11_25"):
        # triple i is sampled from seed + i: the scenes hold the same triples but other noise,
        # and the overall mean is the view-weighted mean of the scenes' means
        assert scores[key] == pytest.approx(np.mean([s[key] for s in scores["per_scene"].values()]))
    # a limit cuts the scenes too
    limited = evaluate_ndn(tmp_path / "model.pt", data, steps=2, limit=count)
    assert list(limited["per_scene"]) == ["heldout_plane_100000"]
    assert limited["abs_rel"] == pytest.approx(limited["per_scene"]["heldout_plane_100000"]["abs_rel"])


def test_unreadable_weights_are_checkpoint_errors(tmp_path):
    with pytest.raises(CheckpointError, match="no NDN weights in this folder"):
        load_checkpoint(tmp_path)
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="cannot read NDN weights"):
        load_checkpoint(tmp_path / "bad.pt")
    torch.save({"format": "something-else"}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not an NDN checkpoint"):
        load_checkpoint(tmp_path / "other.pt")


def test_guided_upsampling_follows_image_edges():
    guide = np.zeros((40, 64, 3), np.uint8)
    guide[:, 33:] = 255  # an edge between columns 32 and 33
    coarse = np.zeros((10, 16), np.float32)
    coarse[:, 8:] = 1.0
    up = guided_upsample(coarse, guide)
    assert up.shape == (40, 64)
    plain = __import__("cv2").resize(coarse, (64, 40), interpolation=__import__("cv2").INTER_LINEAR)
    # the step sits where the image's edge is, sharper than plain bilinear upsampling
    assert abs(up[20, 31] - 0.0) < abs(plain[20, 31] - 0.0) + 1e-6
    assert abs(up[20, 34] - 1.0) < 0.1


def test_priors_command_writes_ndn_maps_in_the_standard_format(scene, tmp_path, capsys):
    weights = perturbed_weights(tmp_path / "weights.pt", tiny_config(), 0.02)
    assert main(["priors", str(scene), "--method", "ndn", "--weights", str(weights), "--steps", "2"]) == 0
    assert "wrote ndn priors for 4 views" in capsys.readouterr().out
    for index in range(4):
        maps = load_prior_maps(scene, "ndn", f"view_{index:03d}.png")
        assert maps.relative_depth and maps.depth.shape == (27, 48) and maps.normal.shape == (27, 48, 3)
        valid = maps.mask
        assert ((maps.depth[valid] >= 1.0) & (maps.depth[valid] <= 2.0)).all() and (maps.depth[~valid] == 0).all()
        np.testing.assert_allclose(np.linalg.norm(maps.normal[valid], axis=-1), 1.0, atol=1e-4)
    first = load_prior_maps(scene, "ndn", "view_001.png").depth.copy()
    assert main(["priors", str(scene), "--method", "ndn", "--weights", str(weights), "--steps", "2"]) == 0
    np.testing.assert_array_equal(load_prior_maps(scene, "ndn", "view_001.png").depth, first)  # seeded
    assert sorted(p.name for p in (scene / "priors").iterdir()) == ["gt", "ndn"]  # no staging left


def test_priors_command_without_weights_uses_the_shipped_weights(scene, capsys, monkeypatch):
    from esgs.core.ndn import shipped

    monkeypatch.delenv("ESGS_NDN_WEIGHTS", raising=False)
    assert main(["priors", str(scene), "--method", "ndn", "--steps", "2"]) == 0
    assert str(shipped.SHIPPED_WEIGHTS) in capsys.readouterr().out
    maps = load_prior_maps(scene, "ndn", "view_000.png")
    assert maps.relative_depth and maps.depth.shape == (27, 48)
    # and a clear error when the package lost them
    monkeypatch.setattr(shipped, "SHIPPED_WEIGHTS", scene / "missing.pt")
    assert main(["priors", str(scene), "--method", "ndn"]) == 1  # a runtime failure
    assert "NDN weights are missing" in capsys.readouterr().err


def test_cli_train_and_eval(scene, tmp_path, capsys):
    data = _data(tmp_path, scene)
    (data / "manifest.json").write_text(json.dumps({"working_size": 32}))
    code = main(["ndn", "train", str(data), "--out", str(tmp_path / "m"), "--steps", "1", "--batch-size", "2",
                 "--base-channels", "8", "--levels", "2", "--time-dim", "16", "--timesteps", "50",
                 "--sample-steps", "2"])
    assert code == 0
    assert (tmp_path / "m/weights.pt").exists() and (tmp_path / "m/events.jsonl").exists()
    _, _, config, _ = load_checkpoint(tmp_path / "m")
    assert config.model.working_size == 32 and config.model.base_channels == 8
    capsys.readouterr()
    assert main(["ndn", "eval", str(tmp_path / "m"), str(data), "--limit", "1", "--json", str(tmp_path / "s.json")]) == 0
    assert json.loads((tmp_path / "s.json").read_text())["views"] == 1


def test_a_failed_run_keeps_the_previous_priors(scene, tmp_path, monkeypatch):
    from esgs.core.ndn import infer

    torch.manual_seed(0)
    model, _ = build_model(tiny_config())
    weights = save_checkpoint(tmp_path / "weights.pt", model, tiny_config())
    infer.write_ndn_priors(scene, weights, steps=1)
    before = {p.relative_to(scene): p.read_bytes() for p in (scene / "priors" / "ndn").rglob("*") if p.is_file()}
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("disk full")
        return original(*args, **kwargs)

    original = infer.maps_from_states
    monkeypatch.setattr(infer, "maps_from_states", failing)
    with pytest.raises(RuntimeError, match="disk full"):
        infer.write_ndn_priors(scene, weights, steps=1, seed=9)
    after = {p.relative_to(scene): p.read_bytes() for p in (scene / "priors" / "ndn").rglob("*") if p.is_file()}
    assert after == before and len(before) == 12
    assert sorted(p.name for p in (scene / "priors").iterdir()) == ["gt", "ndn"]
