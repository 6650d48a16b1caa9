"""benchmarks/ship_ndn.py's card helpers: the data description, the reproduce command and the
output line follow the data folder's manifest and the weights' depth state, not a fixed text."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.conftest import benchmark_script

from esgs.core.ndn.data import plan_scenes



@pytest.fixture(scope="module")
def ship():
    with benchmark_script("ship_ndn") as module:
        yield module


def _data_folder(tmp_path: Path, presets: tuple[str, ...], heldout_presets: tuple[str, ...]) -> Path:
    plan = plan_scenes(12, 4, presets, heldout_presets, validation=2)
    manifest = {"format": "esgs-ndn-shard-1", "working_size": 128, "multiple": 4, "views": 6,
                "resolution": [192, 108], "samples": 4,
                "scenes": [{"split": s, "preset": p, "seed": seed, "shard": f"shards/{s}_{p}_{seed}.npz"}
                           for s, p, seed in plan]}
    (tmp_path / "shards").mkdir(parents=True)
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    return tmp_path


def test_data_plan_and_command_come_from_the_manifest(ship, tmp_path):
    data = _data_folder(tmp_path, ("cratered_plain", "rover_horizon", "dune_field"), ("layered_outcrop",))
    plan = ship.data_plan(data)
    assert plan["presets"] == ["cratered_plain", "rover_horizon", "dune_field"]
    assert plan["heldout_presets"] == ["layered_outcrop"]
    assert plan["count"] == {"train": 12, "validation": 2, "heldout": 4}
    assert (plan["views"], plan["width"], plan["height"], plan["samples"]) == (6, 192, 108, 4)

    command = ship.build_data_command(data, plan)
    assert f"--out {data} --scenes 12 --heldout 4 --validation 2" in command
    assert "--presets cratered_plain rover_horizon dune_field --heldout-presets layered_outcrop" in command
    assert "--views 6 --resolution 192x108 --samples 4 --working-size 128" in command
    # a manifest from before palettes existed was rendered with the fixed look: the command says so
    assert command.endswith("--palette mars")
    # the command is one the CLI accepts: it re-plans the same scenes
    assert plan_scenes(12, 4, tuple(plan["presets"]), tuple(plan["heldout_presets"]), 2) == [
        (s["split"], s["preset"], s["seed"]) for s in json.loads((data / "manifest.json").read_text())["scenes"]]


def test_no_heldout_only_presets_means_no_flag(ship, tmp_path):
    data = _data_folder(tmp_path, ("cratered_plain", "dune_field"), ())
    plan = ship.data_plan(data)
    assert plan["heldout_presets"] == []
    assert "--heldout-presets" not in ship.build_data_command(data, plan)


def test_output_line_follows_the_depth_state(ship):
    assert "affine in true z depth" in ship.output_line({"depth_state": "affine"})
    assert "affine in true z depth" in ship.output_line({})  # weights from before the field: affine
    log_line = ship.output_line({"depth_state": "log", "log_depth_range": 2.5})
    assert "exp(2.5 x state)" in log_line and "affine" not in log_line
    evidence_line = ship.output_line({"depth_state": "log", "log_depth_range": 2.5}, {"evidence": True, "sky": True})
    assert "metres" in evidence_line and "sky probability" in evidence_line and "relative depth" not in evidence_line
    assert "sky" not in ship.output_line({"depth_state": "log"}, {"evidence": True, "sky": False})


def test_train_command_names_a_log_state_only_on_the_first_run(ship):
    def stage(state, init=None):
        config = {"ndn": {"diffusion": {"depth_state": state}}, "train": {"steps": 100, "seed": 0}}
        return {"config": config, "to_step": 100, **({"lineage": {"init_from": init, "init_step": 50}} if init else {})}

    lines = ship.reproduce_train_lines({"stages": [stage("log"), stage("log", init="x")]}, Path("DATA"))
    assert "--depth-state log" in lines[0]
    assert "--depth-state" not in lines[1] and "--init MODEL/checkpoints/step_0000050.pt" in lines[1]
    assert "--depth-state" not in ship.reproduce_train_lines({"stages": [stage("affine")]}, Path("DATA"))[0]


def test_a_fine_tune_of_exported_weights_is_one_stage_described_by_their_provenance(ship, tmp_path):
    import torch

    exported = tmp_path / "shipped.pt"
    torch.save({"format": "esgs-ndn-1", "step": 1000, "provenance": {
        "source": "step_0001000.pt", "step": 1000, "data": "/old/data", "train_seconds": 3600.0, "train_triples": 600,
        "cpu_seconds": {"train": 1800.0, "validation": 360.0},
        "lineage": {"init_from": "/gone/ndn_model/checkpoints/step_0000600.pt", "init_step": 600}}}, exported)
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    checkpoint = run / "checkpoints" / "step_0001200.pt"
    torch.save({"step": 1200, "lineage": {"init_from": str(exported), "init_step": 1000},
                "cpu_seconds": {"train": 720.0, "validation": 72.0}}, checkpoint)
    (run / "config.json").write_text(json.dumps({"train": {"steps": 1200, "seed": 2, "lr_schedule": "cosine",
                                                           "learning_rate": 1e-4, "min_lr_ratio": 0.05,
                                                           "warmup_steps": 50, "ema_decay": 0.999,
                                                           "validation_triples": 0, "batch_size": 8}}))
    events = [{"stage": "ndn-train", "kind": "progress", "step": step, "time": 1000.0 + 3 * (step - 1001)}
              for step in (1001, 1200)]
    (run / "events.jsonl").write_text("\n".join(json.dumps(e) for e in events))

    facts = ship.training_facts(checkpoint, 1200)
    # the exported file's own lineage (a folder that no longer exists) is not followed
    assert [stage.get("exported") for stage in facts["stages"]] == [str(exported), None]
    assert facts["train_seconds"] == 3600.0 + 3 * 199
    first, second = ship.stage_lines(facts)
    assert "Steps 0 -> 1000: the exported weights" in first and "step_0001000.pt" in first and "1.00 h" in first
    assert second.startswith("- Steps 1000 -> 1200")
    commands = ship.reproduce_train_lines(facts, Path("DATA"))
    assert commands[0].startswith("# steps 0-1000: the exported weights")
    assert f"--init {exported}" in commands[1] and "--out MODEL_FT1" in commands[1]


def test_exported_weights_replaced_since_the_fine_tune_lend_no_facts(ship, tmp_path):
    import torch

    exported = tmp_path / "shipped.pt"  # now holds the step-2200 export, the fine-tune started from step 1000
    torch.save({"format": "esgs-ndn-1", "step": 2200, "provenance": {"source": "step_0002200.pt", "step": 2200,
                                                                       "train_seconds": 9000.0}}, exported)
    facts = ship._stage_facts(exported, 1000)
    assert "train_seconds" not in facts
    assert "since replaced" in facts["exported_provenance"]["source"]
