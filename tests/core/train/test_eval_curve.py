"""``eval_every``: the held-out views evaluated every K steps during a run (events.jsonl "eval"
events with the training seconds so far), without changing the training."""
from __future__ import annotations

import json

import pytest
import torch

from esgs.core.cli import main
from esgs.core.config import config_to_dict
from esgs.core.train import TrainHook, train
from esgs.core.train.checkpoint import list_checkpoints, load_checkpoint
from esgs.core.train.config import run_config_from_dict

from .conftest import train_then_checkpoint


class _StepLosses(TrainHook):
    name = "step_losses"

    def __init__(self):
        self.total: list[float] = []

    def after_backward(self, run, context) -> None:
        self.total.append(float(context.loss.detach()))


def _events(run) -> list[dict]:
    return [json.loads(line) for line in (run / "events.jsonl").read_text().splitlines()]


def _final_params(run) -> dict:
    return load_checkpoint(list_checkpoints(run / "checkpoints")[-1][1])["gaussians"]["params"]


def test_evaluating_during_training_changes_nothing_and_writes_the_curve(fast_config, tmp_path):
    # densification inside the run, so the evaluations fall between densifications too
    settings = dict(iterations=14, densify_from=4000, densify_until=15000, max_gaussians=400)
    plain_losses, curve_losses = _StepLosses(), _StepLosses()
    plain = train(fast_config(out=tmp_path / "plain", **settings), hooks=[plain_losses])
    curved = train(fast_config(out=tmp_path / "curve", eval_every=4, **settings), hooks=[curve_losses])

    assert curve_losses.total == plain_losses.total  # every step's loss, bitwise
    a, b = _final_params(tmp_path / "plain"), _final_params(tmp_path / "curve")
    for name, value in a.items():
        assert torch.equal(value, b[name]), name
    assert curved.n_gaussians == plain.n_gaussians
    assert curved.metrics["psnr"] == plain.metrics["psnr"]

    evals = [event for event in _events(tmp_path / "curve") if event["kind"] == "eval"]
    assert [event["step"] for event in evals] == [4, 8, 12, 14]  # the last: the end-of-run evaluation
    assert all(event["stage"] == "eval" and event["total"] == 14 for event in evals)
    seconds = [event["metrics"]["train_s"] for event in evals]
    assert all(0.0 < earlier < later for earlier, later in zip(seconds, seconds[1:]))
    assert seconds[-1] == pytest.approx(curved.train_s)
    assert curved.train_s <= curved.elapsed_s
    for event in evals:
        assert set(event["metrics"]) == {"psnr", "ssim", "train_s", "n_gaussians"}
        assert 0.0 < event["metrics"]["ssim"] <= 1.0
    assert evals[-1]["metrics"]["psnr"] == pytest.approx(curved.metrics["psnr"])
    assert evals[-1]["metrics"]["n_gaussians"] == curved.n_gaussians
    assert not [event for event in _events(tmp_path / "plain") if event["kind"] == "eval"]
    saved = json.loads((tmp_path / "curve" / "train_result.json").read_text())
    assert saved["train_s"] == pytest.approx(curved.train_s)


def test_evaluation_time_is_not_training_time(fast_config, tmp_path, monkeypatch):
    import time

    from esgs.core.train import trainer as trainer_module

    original = trainer_module.Trainer._evaluate_held_out

    def slow(self, model, **options):
        time.sleep(0.3)
        return original(self, model, **options)

    monkeypatch.setattr(trainer_module.Trainer, "_evaluate_held_out", slow)
    # no pruning pass (it renders every training view once): only the steps are on the clock
    result = train(fast_config(iterations=6, eval_every=2, prune_hidden=0.0))
    evals = [event for event in _events(result.run_dir) if event["kind"] == "eval"]
    assert [event["step"] for event in evals] == [2, 4, 6]
    # two mid-run evaluations of 0.3 s each are off the clock; the end-of-run one counts in elapsed_s only
    assert result.train_s < 0.6
    assert result.elapsed_s >= result.train_s + 0.3


def test_the_method_shows_its_exported_model_and_keeps_training_the_same(fast_config, tmp_path):
    # GPDFN: export_model folds the residual field into a copy of the Gaussians
    from esgs.core.experiments.bench import full_esgs_without_priors
    from esgs.core.methods import train as train_method

    settings = dict(iterations=6, method="esgs", method_config=full_esgs_without_priors())
    plain = train_method(fast_config(out=tmp_path / "plain", **settings))
    curved = train_method(fast_config(out=tmp_path / "curve", eval_every=2, **settings))
    a, b = _final_params(tmp_path / "plain"), _final_params(tmp_path / "curve")
    for name, value in a.items():
        assert torch.equal(value, b[name]), name
    assert curved.metrics["psnr"] == plain.metrics["psnr"]
    assert [e["step"] for e in _events(tmp_path / "curve") if e["kind"] == "eval"] == [2, 4, 6]


def test_the_setting_round_trips_older_runs_read_without_it_and_it_may_change_on_resume(fast_config):
    config = fast_config(eval_every=5)
    saved = config_to_dict(config)
    assert run_config_from_dict(json.loads(json.dumps(saved))).eval_every == 5
    del saved["eval_every"]  # a run saved before the setting existed
    assert run_config_from_dict(saved).eval_every == 0
    # evaluating changes nothing of the training: a run may resume with another eval_every
    first = fast_config(iterations=8, evaluate=False, checkpoint_every=4)
    train_then_checkpoint(first, 4)
    resumed = train(fast_config(iterations=8, evaluate=False, checkpoint_every=4, resume=True, eval_every=3))
    assert resumed.step == 8
    assert [event["step"] for event in _events(resumed.run_dir) if event["kind"] == "eval"] == [6]


def test_negative_is_refused(fast_config):
    from esgs.core.errors import ConfigError

    with pytest.raises(ConfigError, match="eval_every"):
        fast_config(eval_every=-1).validate()


def test_the_command_line_flag(tiny_scene, tmp_path, capsys):
    run = tmp_path / "run"
    code = main(["train", str(tiny_scene), "--out", str(run), "--iterations", "4", "--backend", "reference",
                 "--threads", "1", "--no-lpips", "--quiet", "--no-save-renders", "--eval-every", "2"])
    assert code == 0, capsys.readouterr().err
    assert json.loads((run / "config.json").read_text())["eval_every"] == 2
    assert [event["step"] for event in _events(run) if event["kind"] == "eval"] == [2, 4]


def test_tensorboard_gets_the_curve(fast_config, tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    board = tmp_path / "board"
    train(fast_config(iterations=6, eval_every=2, tensorboard=board))
    accumulator = EventAccumulator(str(board), size_guidance={"scalars": 0})
    accumulator.Reload()
    assert [event.step for event in accumulator.Scalars("eval/psnr")] == [2, 4, 6]
    assert [event.step for event in accumulator.Scalars("eval/ssim")] == [2, 4, 6]


def test_the_console_prints_an_evaluation_beside_the_training_bar():
    import io

    from esgs.core.progress import ConsoleProgress, ProgressEvent

    stream = io.StringIO()
    console = ConsoleProgress(stream=stream, min_interval_s=0.0)
    console(ProgressEvent(step=5, total=10, stage="train", metrics={"loss": 0.1}))
    bar = console._bar
    console(ProgressEvent(step=5, total=10, stage="eval", kind="eval",
                          metrics={"psnr": 21.5, "ssim": 0.7, "train_s": 3.25, "n_gaussians": 9}))
    assert console._bar is bar and console._stage == "train"  # the training bar goes on
    assert "step 5: held-out PSNR 21.5 dB, SSIM 0.7 after 3.25 s of training" in stream.getvalue()
    console.close()
