"""The NDN weights shipped in the package: small, loadable, and as good as the model card says."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from esgs.core.errors import CheckpointError
from esgs.core.ndn import shipped
from esgs.core.ndn.infer import evaluate_arrays, mean_scores
from esgs.core.ndn.model import parameter_count
from esgs.core.ndn.train import build_model, load_checkpoint, save_checkpoint

from .conftest import tiny_config

REPO = Path(__file__).resolve().parents[3]
FIXTURES = REPO / "tests" / "core" / "fixtures" / "ndn"
CARD = REPO / "docs" / "ndn_model_card.md"
# the slice is re-scored with the same seeds; only float differences between CPUs remain
TOLERANCE = {"abs_rel": 0.005, "delta1": 0.01, "normal_mean_deg": 0.5, "normal_within_11_25": 0.01}


def fmt(key: str, value: float) -> str:
    """The model card's number format (benchmarks/ship_ndn.py writes it)."""
    return f"{value:.2f}" if key == "normal_mean_deg" else f"{100 * value:.1f} %" if key == "normal_within_11_25" \
        else f"{value:.4f}"


def test_shipped_weights_are_small_half_precision_and_load():
    path = shipped.shipped_weights()
    assert path.stat().st_size < 8e6
    payload = torch.load(path, map_location="cpu", weights_only=True)
    assert payload["dtype"] == "float16" and "optimizer" not in payload
    assert all(t.dtype == torch.float16 for t in payload["model"].values() if t.is_floating_point())
    model, diffusion, config, _ = load_checkpoint(path)
    assert all(p.dtype == torch.float32 for p in model.parameters())
    assert parameter_count(model) <= 5_000_000 and config.model.working_size <= 128
    assert diffusion.config.prediction in ("v", "epsilon")


def test_default_weights_are_the_shipped_ones_unless_named(monkeypatch, tmp_path):
    monkeypatch.delenv(shipped.WEIGHTS_ENVIRONMENT_VARIABLE, raising=False)
    assert shipped.resolve_default_weights() == shipped.SHIPPED_WEIGHTS
    monkeypatch.setenv(shipped.WEIGHTS_ENVIRONMENT_VARIABLE, str(tmp_path / "env.pt"))
    assert shipped.resolve_default_weights() == tmp_path / "env.pt"
    assert shipped.resolve_default_weights(tmp_path / "given.pt") == tmp_path / "given.pt"
    monkeypatch.delenv(shipped.WEIGHTS_ENVIRONMENT_VARIABLE)
    monkeypatch.setattr(shipped, "SHIPPED_WEIGHTS", tmp_path / "missing.pt")
    with pytest.raises(CheckpointError, match="package's NDN weights are missing"):
        shipped.resolve_default_weights()


def test_export_keeps_the_network_and_drops_the_training_state(tmp_path):
    torch.manual_seed(0)
    model, diffusion = build_model(tiny_config("v"))
    for parameter in model.parameters():
        parameter.data.add_(0.05 * torch.randn_like(parameter))
    optimizer = torch.optim.AdamW(model.parameters())
    sum(parameter.sum() for parameter in model.parameters()).backward()
    optimizer.step()  # so the checkpoint carries optimiser moments, as training's do
    checkpoint = save_checkpoint(tmp_path / "step_5.pt", model, tiny_config("v"), step=5, optimizer=optimizer,
                                 generator=torch.Generator().manual_seed(1))
    out = shipped.export_weights(checkpoint, tmp_path / "w" / "small.pt", provenance={"source": "step_5.pt"})
    payload = torch.load(out, map_location="cpu", weights_only=True)
    assert payload["step"] == 5 and payload["provenance"] == {"source": "step_5.pt"}
    assert "optimizer" not in payload and "generator" not in payload
    assert out.stat().st_size < checkpoint.stat().st_size / 2
    loaded, _, _, _ = load_checkpoint(out)
    views = torch.rand(2, 9, 16, 32) * 2 - 1
    state = torch.randn(2, 1, 16, 32), torch.randn(2, 3, 16, 32), torch.tensor([3, 40])
    with torch.no_grad():
        expected, got = model.eval()(views, *state), loaded(views, *state)
    for a, b in zip(expected, got):
        assert (a - b).abs().max() < 2e-2 * max(1.0, float(a.abs().max()))  # float16 rounding only
        assert (a - b).abs().max() > 0  # it really was stored in half precision


def test_shipped_weights_reproduce_the_model_card_on_the_heldout_slice():
    expected = json.loads((FIXTURES / "heldout_slice_scores.json").read_text())
    weights = shipped.shipped_weights()
    assert hashlib.sha256(weights.read_bytes()).hexdigest() == expected["weights_sha256"], \
        "the shipped weights changed without re-running benchmarks/ship_ndn.py"
    with np.load(FIXTURES / "heldout_slice.npz", allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files}
    assert len(arrays["views"]) == len(expected["names"]) >= 2
    model, diffusion, _, payload = load_checkpoint(weights)
    assert payload["step"] == expected["step"]
    torch.set_num_threads(1)
    scores = mean_scores(evaluate_arrays(model, diffusion, arrays, steps=expected["ddim_steps"], seed=expected["seed"]))
    for key, tolerance in TOLERANCE.items():
        assert abs(scores[key] - expected["scores"][key]) <= tolerance, (key, scores[key], expected["scores"][key])
    # the model card states the same figures for this slice and the same training step
    card = CARD.read_text()
    row = "| heldout_slice | " + " | ".join(fmt(key, expected["scores"][key]) for key in TOLERANCE) + " |"
    assert row in card
    assert f"training step **{expected['step']}**" in card


COMPLETION_CARD = REPO / "docs" / "ndn_completion_model_card.md"
COMPLETION_TOLERANCE = {"normal_mean_deg": 0.5, "normal_within_11_25": 0.01, "abs_rel_metric": 0.005,
                        "delta1_metric": 0.01}


def completion_fmt(key: str, value: float) -> str:
    """benchmarks/ship_completion.py's number format."""
    return f"{value:.2f}" if key == "normal_mean_deg" else f"{100 * value:.1f} %" \
        if key.startswith(("normal_w", "delta")) else f"{value:.4f}"


def test_shipped_normal_weights_are_a_small_half_precision_evidence_network():
    path = shipped.shipped_normal_weights()
    assert path.stat().st_size < 8e6
    payload = torch.load(path, map_location="cpu", weights_only=True)
    assert payload["dtype"] == "float16" and "optimizer" not in payload
    model, _, config, _ = load_checkpoint(path)
    assert config.model.evidence and config.model.sky and config.diffusion.prediction == "regression"
    assert parameter_count(model) <= 5_000_000 and config.model.working_size <= 128


def test_shipped_normal_weights_reproduce_their_model_card_on_the_slice_with_evidence():
    expected = json.loads((FIXTURES / "completion_slice_scores.json").read_text())
    weights = shipped.shipped_normal_weights()
    assert hashlib.sha256(weights.read_bytes()).hexdigest() == expected["weights_sha256"], \
        "the shipped normal weights changed without re-running benchmarks/ship_completion.py"
    with np.load(FIXTURES / "completion_slice.npz", allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files if key != "names"}
    assert len(arrays["views"]) == len(expected["names"]) >= 2 and arrays["stereo_depth"].any()
    model, diffusion, _, payload = load_checkpoint(weights)
    assert payload["step"] == expected["step"]
    torch.set_num_threads(1)
    scores = mean_scores(evaluate_arrays(model, diffusion, arrays, seed=expected["seed"],
                                         evidence_mode=expected["evidence"]))
    for key, tolerance in COMPLETION_TOLERANCE.items():
        assert abs(scores[key] - expected["scores"][key]) <= tolerance, (key, scores[key], expected["scores"][key])
    # without the evidence the same network answers differently: the slice really tests it
    blind = mean_scores(evaluate_arrays(model, diffusion, arrays, seed=expected["seed"], evidence_mode="none"))
    assert "abs_rel_metric" not in blind and abs(blind["normal_mean_deg"] - scores["normal_mean_deg"]) > 0.01
    card = COMPLETION_CARD.read_text()
    row = "| completion_slice | " + " | ".join(completion_fmt(k, expected["scores"][k]) for k in COMPLETION_TOLERANCE) + " |"
    assert row in card
    assert f"training step **{expected['step']}**" in card
