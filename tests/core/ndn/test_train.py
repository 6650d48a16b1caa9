"""NDN training: learning-rate schedule, weight average, validation split, exact resume, fine-tuning."""
from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from esgs.core.errors import ConfigError, DatasetError
from esgs.core.ndn.config import NDNTrainConfig
from esgs.core.ndn.data import (HELDOUT_SEED_OFFSET, VALIDATION_SEED_OFFSET, check_disjoint_splits, plan_scenes,
                                scene_triples, shard_scene, write_shard)
from esgs.core.ndn.shipped import export_weights
from esgs.core.ndn.train import (WeightAverage, best_checkpoint, learning_rate_at, load_checkpoint, selection_score,
                                 train_ndn, validation_subset)

from .conftest import make_scene, tiny_config


def _data(tmp_path, validation: bool = True):
    """Train / validation / held-out shards from three different scenes (different textures)."""
    data = tmp_path / "data"
    for split, seed, name in (("train", 0, "train_plane_1"), ("validation", 1, f"validation_plane_{VALIDATION_SEED_OFFSET}"),
                              ("heldout", 2, f"heldout_plane_{HELDOUT_SEED_OFFSET}")):
        if split == "validation" and not validation:
            continue
        scene = make_scene(tmp_path / f"scene_{split}", seed=seed)
        write_shard(data / "shards" / f"{name}.npz", scene_triples(scene, 32, 2), {})
    return data


def _settings(**overrides) -> NDNTrainConfig:
    values = dict(steps=4, batch_size=2, checkpoint_every=2, seed=0, threads=1, learning_rate=1e-3,
                  ema_decay=0.9, validation_triples=2)
    values.update(overrides)
    return NDNTrainConfig(**values)


def test_learning_rate_schedules():
    cosine = NDNTrainConfig(steps=110, learning_rate=1e-3, min_lr_ratio=0.1, lr_schedule="cosine")
    # a schedule starting after step 10 (a fine-tune): 100 steps from the peak to the floor
    assert learning_rate_at(11, cosine, 10) == pytest.approx(1e-4 + 9e-4 * 0.5 * (1 + math.cos(math.pi * 0.01)))
    assert learning_rate_at(60, cosine, 10) == pytest.approx(5.5e-4)  # halfway: the mean of peak and floor
    assert learning_rate_at(110, cosine, 10) == pytest.approx(1e-4)
    assert learning_rate_at(500, cosine, 10) == pytest.approx(1e-4)  # stays at the floor past the end
    linear = NDNTrainConfig(steps=100, learning_rate=1e-3, min_lr_ratio=0.0, lr_schedule="linear", warmup_steps=20)
    assert learning_rate_at(5, linear) == pytest.approx(2.5e-4)  # warm-up: 5/20 of the peak
    assert learning_rate_at(20, linear) == pytest.approx(1e-3)
    assert learning_rate_at(60, linear) == pytest.approx(5e-4)  # half of the 80 decay steps done
    assert learning_rate_at(100, linear) == pytest.approx(0.0, abs=1e-12)
    constant = NDNTrainConfig(steps=100, learning_rate=3e-4, lr_schedule="constant")
    assert {learning_rate_at(step, constant) for step in (1, 50, 100)} == {3e-4}
    values = [learning_rate_at(step, cosine, 10) for step in range(11, 111)]
    assert all(a >= b for a, b in zip(values, values[1:]))
    with pytest.raises(ConfigError, match="lr_schedule"):
        NDNTrainConfig(lr_schedule="step").validate()
    with pytest.raises(ConfigError, match="ema_decay"):
        NDNTrainConfig(ema_decay=1.0).validate()


def test_weight_average_update_maths():
    layer = torch.nn.Linear(2, 1)
    with torch.no_grad():
        layer.weight.fill_(1.0)
        layer.bias.fill_(0.0)
    average = WeightAverage(layer, decay=0.5)
    expected = torch.ones(1, 2)
    for update, value in enumerate((3.0, -1.0, 2.0, 5.0), start=1):
        with torch.no_grad():
            layer.weight.fill_(value)
        average.update(layer)
        decay = min(0.5, (1 + update) / (10 + update))  # warm-up 2/11, 3/12, 4/13, then capped at 0.5
        expected = decay * expected + (1 - decay) * value
        torch.testing.assert_close(average.weights["weight"], expected)
    assert average.updates == 4 and average.decay_at(9) == 0.5 and average.decay_at(1) == pytest.approx(2 / 11)
    # the average is a copy: the model keeps its own weights
    assert float(layer.weight.detach()[0, 0]) == 5.0
    restored = WeightAverage(layer, decay=0.1)
    restored.load_state_dict(average.state_dict())
    assert restored.updates == 4 and restored.decay == 0.5
    torch.testing.assert_close(restored.weights["weight"], expected)


def test_selection_score_and_validation_subset():
    assert selection_score({"abs_rel": 0.065, "delta1": 0.973, "normal_mean_deg": 20.0}) == pytest.approx(3.0)
    assert selection_score({"abs_rel": 0.0, "delta1": 1.0, "normal_mean_deg": 0.0}) == 0.0
    arrays = {"views": np.arange(40), "depth": np.arange(40) * 2}
    subset = validation_subset(arrays, 5)
    np.testing.assert_array_equal(subset["views"], [0, 10, 20, 29, 39])
    np.testing.assert_array_equal(subset["depth"], subset["views"] * 2)
    assert validation_subset(arrays, 0)["views"].shape == (40,) and validation_subset(arrays, 99) is arrays


def test_validation_split_never_overlaps_training_or_held_out(tmp_path):
    presets = ("cratered_plain", "dune_field", "rocky_slope")
    plan = plan_scenes(30, 4, presets, heldout_presets=("layered_outcrop",), validation=6)
    splits = {split: {(p, s) for sp, p, s in plan if sp == split} for split in ("train", "validation", "heldout")}
    assert [len(v) for v in splits.values()] == [30, 6, 4]
    assert not (splits["train"] & splits["validation"]) and not (splits["validation"] & splits["heldout"])
    seeds = {split: {s for _, s in pairs} for split, pairs in splits.items()}
    assert max(seeds["train"]) < VALIDATION_SEED_OFFSET <= min(seeds["validation"])
    assert max(seeds["validation"]) < HELDOUT_SEED_OFFSET <= min(seeds["heldout"])
    assert {p for p, _ in splits["validation"]} == set(presets)  # the training presets, new seeds
    with pytest.raises(ConfigError, match="validation seeds"):
        plan_scenes(VALIDATION_SEED_OFFSET * 3, 0, presets)
    assert shard_scene("shards/validation_rocky_slope_50002.npz") == ("validation", "rocky_slope", 50002)
    assert shard_scene("shards/heldout_landform_orbit_1.npz") == ("heldout", "landform_orbit", 1)
    assert shard_scene("shards/other.npz") is None

    data = _data(tmp_path)
    check_disjoint_splits(data)  # three different scenes: fine
    # the same scene under a validation name, or the same images under another name, are refused
    shutil.copy(data / "shards/train_plane_1.npz", data / "shards/validation_other_50007.npz")
    with pytest.raises(DatasetError, match="also in the 'train' split"):
        check_disjoint_splits(data)
    (data / "shards/validation_other_50007.npz").unlink()
    shutil.copy(data / f"shards/validation_plane_{VALIDATION_SEED_OFFSET}.npz", data / "shards/train_plane_50000.npz")
    with pytest.raises(DatasetError, match="seed 50000 is in the 'train' and the 'validation' splits"):
        check_disjoint_splits(data)
    with pytest.raises(DatasetError):
        train_ndn(data, tmp_path / "refused", _settings(steps=1), tiny_config())


def test_sigterm_saves_the_step_it_finished_and_resume_equals_the_uninterrupted_run(tmp_path):
    import os
    import signal

    data = _data(tmp_path)
    settings = _settings(steps=5, checkpoint_every=4)
    straight = train_ndn(data, tmp_path / "straight", settings, tiny_config())
    assert straight["status"] == "completed"
    events = []

    def terminate_during_step_3(event):
        events.append(event)
        if event.stage == "ndn-train" and event.kind == "progress" and event.step == 3:
            os.kill(os.getpid(), signal.SIGTERM)  # arrives mid-run; the step in progress finishes

    previous = signal.getsignal(signal.SIGTERM)
    stopped = train_ndn(data, tmp_path / "split", settings, tiny_config(), progress=terminate_during_step_3)
    assert signal.getsignal(signal.SIGTERM) is previous  # the handler is put back
    assert stopped["status"] == "interrupted" and stopped["steps"] == 3 and stopped["stopped_by"] == "SIGTERM"
    # step 3 is no checkpoint step (every 4), yet it is saved; no final weights for an unfinished run
    assert sorted(p.name for p in (tmp_path / "split/checkpoints").iterdir()) == ["step_0000003.pt"]
    assert not (tmp_path / "split/weights.pt").exists()
    assert json.loads((tmp_path / "split/train_summary.json").read_text())["status"] == "interrupted"
    assert any(e.kind == "message" and "--resume" in (e.message or "") for e in events)
    resumed = train_ndn(data, tmp_path / "split", settings, resume=True)
    assert resumed["status"] == "completed" and resumed["resumed_from"] == 3
    a = torch.load(tmp_path / "straight/weights.pt", weights_only=True)
    b = torch.load(tmp_path / "split/weights.pt", weights_only=True)
    for name in a["model"]:
        torch.testing.assert_close(a["model"][name], b["model"][name], rtol=0, atol=0)


def test_resume_restores_weights_average_optimiser_and_schedule_exactly(tmp_path):
    data = _data(tmp_path)
    straight = train_ndn(data, tmp_path / "straight", _settings(), tiny_config())
    events = []

    class Crash(Exception):
        pass

    def crash_at_step_3(event):
        if event.stage == "ndn-train" and event.step == 3:
            raise Crash  # the process dies after step 3, whose state was never saved

    with pytest.raises(Crash):
        train_ndn(data, tmp_path / "split", _settings(), tiny_config(), progress=crash_at_step_3)
    assert sorted(p.name for p in (tmp_path / "split/checkpoints").iterdir()) == ["step_0000002.pt"]
    resumed = train_ndn(data, tmp_path / "split", _settings(), resume=True, progress=events.append)
    assert resumed["resumed_from"] == 2 and straight["steps"] == resumed["steps"] == 4
    # the resumed half follows the schedule of the whole run (cosine from 1e-3 over steps 1..4)
    lrs = [e.metrics["lr"] for e in events if e.stage == "ndn-train" and e.kind == "progress"]
    assert lrs == pytest.approx([learning_rate_at(step, _settings()) for step in (3, 4)])
    a = torch.load(tmp_path / "straight/checkpoints/step_0000004.pt", weights_only=True)
    b = torch.load(tmp_path / "split/checkpoints/step_0000004.pt", weights_only=True)
    for name in a["model"]:
        torch.testing.assert_close(a["model"][name], b["model"][name], rtol=0, atol=0)
        torch.testing.assert_close(a["ema"]["weights"][name], b["ema"]["weights"][name], rtol=0, atol=0)
    assert a["ema"]["updates"] == b["ema"]["updates"] == 4
    moments_a, moments_b = a["optimizer"]["state"], b["optimizer"]["state"]
    assert moments_a.keys() == moments_b.keys()
    for key in moments_a:
        torch.testing.assert_close(moments_a[key]["exp_avg_sq"], moments_b[key]["exp_avg_sq"], rtol=0, atol=0)
    assert b["cpu_seconds"]["train"] > 0 and b["cpu_seconds"]["validation"] > 0
    # the average differs from the raw weights, and it is what evaluation and export use
    name = next(n for n, t in a["model"].items() if t.is_floating_point() and t.numel() > 10)
    assert not torch.equal(a["model"][name], a["ema"]["weights"][name])
    evaluated, _, _, _ = load_checkpoint(tmp_path / "split/checkpoints/step_0000004.pt")
    raw, _, _, _ = load_checkpoint(tmp_path / "split/checkpoints/step_0000004.pt", ema=False)
    torch.testing.assert_close(evaluated.state_dict()[name], a["ema"]["weights"][name])
    torch.testing.assert_close(raw.state_dict()[name], a["model"][name])
    final, _, _, _ = load_checkpoint(tmp_path / "split")  # weights.pt holds the average
    torch.testing.assert_close(final.state_dict()[name], a["ema"]["weights"][name])
    shipped, _, _, slim = load_checkpoint(export_weights(tmp_path / "split/checkpoints/step_0000004.pt",
                                                         tmp_path / "ship.pt"))
    assert slim["weights"] == "ema"
    torch.testing.assert_close(shipped.state_dict()[name], a["ema"]["weights"][name].half().float())
    # inference settings can travel with exported weights
    _, diffusion, config, _ = load_checkpoint(export_weights(
        tmp_path / "split/checkpoints/step_0000004.pt", tmp_path / "ship3.pt",
        sampling={"sample_steps": 2, "sample_ensemble": 3, "sample_reduce": "mean"}))
    assert (config.diffusion.sample_steps, config.diffusion.sample_ensemble, config.diffusion.sample_reduce) == \
        (2, 3, "mean") and diffusion.config.sample_ensemble == 3
    with pytest.raises(ConfigError, match="sample_ensemble"):
        export_weights(tmp_path / "split/checkpoints/step_0000004.pt", tmp_path / "bad.pt",
                       sampling={"sample_ensemble": 0})


def test_validation_scores_every_checkpoint_and_names_the_best(tmp_path):
    data = _data(tmp_path)
    events = []
    summary = train_ndn(data, tmp_path / "model", _settings(validation_steps=2, validation_ensemble=3,
                                                                  validation_reduce="mean"), tiny_config(),
                        progress=events.append)
    record = json.loads((tmp_path / "model/validation.json").read_text())
    assert [entry["step"] for entry in record["checkpoints"]] == [2, 4]
    for entry in record["checkpoints"]:
        assert entry["triples"] == 2 and entry["score"] == pytest.approx(selection_score(entry))
        assert (entry["ddim_steps"], entry["ensemble"], entry["reduce"]) == (2, 3, "mean")  # validation's own settings
    assert record["best"] == min(record["checkpoints"], key=lambda entry: entry["score"])
    assert summary["best_validation"] == record["best"]
    assert best_checkpoint(tmp_path / "model") == tmp_path / "model/checkpoints" / record["best"]["checkpoint"]
    payload = torch.load(tmp_path / "model/checkpoints/step_0000002.pt", weights_only=True)
    assert payload["validation"]["score"] == record["checkpoints"][0]["score"]
    # the scores are those of `evaluate_arrays` on the averaged weights with these settings
    from esgs.core.ndn.data import load_shards
    from esgs.core.ndn.infer import evaluate_arrays, mean_scores

    model, diffusion, _, _ = load_checkpoint(tmp_path / "model/checkpoints/step_0000004.pt")
    assert diffusion.config.sample_reduce == "median"  # the saved model's own setting is untouched
    diffusion.config.sample_reduce = "mean"
    arrays = validation_subset(load_shards(data, "validation"), 2)
    again = mean_scores(evaluate_arrays(model, diffusion, arrays, seed=0, steps=2, ensemble=3))
    assert again["abs_rel"] == pytest.approx(record["checkpoints"][1]["abs_rel"], abs=1e-6)
    assert again["normal_mean_deg"] == pytest.approx(record["checkpoints"][1]["normal_mean_deg"], abs=1e-4)
    assert [e.step for e in events if e.stage == "ndn-validation"] == [2, 4]
    # without validation shards nothing is scored (and nothing breaks)
    train_ndn(_data(tmp_path / "plain", validation=False), tmp_path / "plain_model", _settings(steps=2),
              tiny_config())
    assert not (tmp_path / "plain_model/validation.json").exists() and best_checkpoint(tmp_path / "plain_model") is None


def test_fine_tuning_continues_the_step_count_with_a_new_schedule(tmp_path):
    data = _data(tmp_path, validation=False)
    train_ndn(data, tmp_path / "base", _settings(steps=2, ema_decay=0.0, lr_schedule="constant"), tiny_config())
    init = tmp_path / "base/checkpoints/step_0000002.pt"
    events = []
    settings = _settings(steps=5, init=str(init), seed=1, min_lr_ratio=0.0, lr_schedule="linear")
    summary = train_ndn(data, tmp_path / "tuned", settings, progress=events.append)
    assert summary["resumed_from"] == 2 and summary["init_step"] == 2 and summary["init_from"] == str(init.resolve())
    lrs = [e.metrics["lr"] for e in events if e.kind == "progress"]
    assert lrs == pytest.approx([1e-3 * 2 / 3, 1e-3 / 3, 0.0], abs=1e-12)  # 3 steps from the peak to 0
    payload = torch.load(tmp_path / "tuned/checkpoints/step_0000005.pt", weights_only=True)
    assert payload["schedule_start"] == 2 and payload["lineage"]["init_step"] == 2
    config = json.loads((tmp_path / "tuned/config.json").read_text())
    assert config["init_step"] == 2 and config["schedule_start"] == 2
    # the starting checkpoint's optimiser moments carried over (Adam's step count continues)
    assert int(payload["optimizer"]["state"][0]["step"]) == 5
    # a resume of the fine-tune keeps its schedule start (not the init's, not 0)
    more = train_ndn(data, tmp_path / "tuned", _settings(steps=6, init=str(init), lr_schedule="linear"), resume=True)
    assert more["resumed_from"] == 5
    assert torch.load(tmp_path / "tuned/checkpoints/step_0000006.pt", weights_only=True)["schedule_start"] == 2
