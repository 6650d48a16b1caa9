"""``esgs train ... --tensorboard DIR``: TensorBoard scalars beside events.jsonl, read back with
TensorBoard's own reader; the error when the optional package is missing."""
from __future__ import annotations

import json
import sys

import pytest

from esgs.core.cli import main
from esgs.core.config import config_to_dict
from esgs.core.train import TrainHook, train
from esgs.core.train.config import run_config_from_dict

pytest.importorskip("tensorboard")
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator


def _scalars(folder) -> dict[str, list[tuple[int, float]]]:
    """tag -> [(step, value)] of every scalar in the event files of ``folder``."""
    accumulator = EventAccumulator(str(folder), size_guidance={"scalars": 0})
    accumulator.Reload()
    return {tag: [(event.step, event.value) for event in accumulator.Scalars(tag)]
            for tag in accumulator.Tags()["scalars"]}


class _StepLosses(TrainHook):
    """Records every step's total loss and unweighted loss terms, as the trainer computed them."""

    name = "step_losses"

    def __init__(self):
        self.total: dict[int, float] = {}
        self.terms: dict[int, dict[str, float]] = {}

    def after_backward(self, run, context) -> None:
        self.total[context.step] = float(context.loss.detach())
        self.terms[context.step] = dict(context.loss_values)


def test_scalars_are_written_and_match_the_run(fast_config, tmp_path):
    board = tmp_path / "board"
    config = fast_config(iterations=12, progress_every=5, tensorboard=board)
    losses = _StepLosses()
    result = train(config, hooks=[losses])
    scalars = _scalars(board)

    expected = {"train/loss", "train/psnr", "train/n_gaussians", "train/s_per_step", "loss/total", "loss/l1",
                "loss/dssim", "eval/psnr", "eval/ssim"}
    expected |= {f"lr/{group}" for group in ("means", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats", "sky")}
    assert expected <= set(scalars), sorted(scalars)
    assert "eval/lpips" not in scalars  # not computed (lpips=False): no made-up value

    # the same steps as the progress events of events.jsonl, and the same numbers
    lines = [json.loads(line) for line in (config.out / "events.jsonl").read_text().splitlines()]
    progress = {line["step"]: line["metrics"] for line in lines if line["kind"] == "progress" and line["stage"] == "train"}
    assert sorted(progress) == [5, 10, 12]
    for tag in ("train/loss", "train/psnr", "train/n_gaussians", "train/s_per_step", "loss/total", "lr/means"):
        assert [step for step, _ in scalars[tag]] == [5, 10, 12], tag
    for key in ("loss", "psnr", "n_gaussians", "s_per_step"):
        assert [value for _, value in scalars[f"train/{key}"]] == pytest.approx(
            [progress[step][key] for step in (5, 10, 12)], rel=1e-6), key
    assert scalars["train/n_gaussians"][-1][1] == result.n_gaussians

    # the raw per-step values (TensorBoard smooths on its own) are the trainer's
    for step, value in scalars["loss/total"]:
        assert value == pytest.approx(losses.total[step], rel=1e-6)
    for term in ("l1", "dssim"):
        assert [value for _, value in scalars[f"loss/{term}"]] == pytest.approx(
            [losses.terms[step][term] for step in (5, 10, 12)], rel=1e-6)
    assert all(value == pytest.approx(config.feature_lr) for _, value in scalars["lr/sh_dc"])
    means_lr = [value for _, value in scalars["lr/means"]]
    assert means_lr[0] > means_lr[-1] > 0  # the position schedule decays

    metrics = json.loads((config.out / "metrics.json").read_text())
    assert scalars["eval/psnr"] == [(12, pytest.approx(metrics["psnr"], rel=1e-6))]
    assert scalars["eval/ssim"] == [(12, pytest.approx(metrics["ssim"], rel=1e-6))]


def test_the_setting_is_saved_and_older_runs_read_without_it(fast_config, tmp_path):
    config = fast_config(tensorboard=tmp_path / "board")
    saved = config_to_dict(config)
    assert saved["tensorboard"] == str(tmp_path / "board")
    assert run_config_from_dict(json.loads(json.dumps(saved))).tensorboard == tmp_path / "board"
    del saved["tensorboard"]  # a run saved before the setting existed
    assert run_config_from_dict(saved).tensorboard is None


def test_the_command_line_flag(tiny_scene, tmp_path, capsys):
    run, board = tmp_path / "run", tmp_path / "board"
    code = main(["train", str(tiny_scene), "--out", str(run), "--iterations", "4", "--backend", "reference",
                 "--threads", "1", "--no-lpips", "--quiet", "--no-evaluate", "--progress-every", "2",
                 "--tensorboard", str(board)])
    assert code == 0, capsys.readouterr().err
    assert json.loads((run / "config.json").read_text())["tensorboard"] == str(board)
    assert [step for step, _ in _scalars(board)["train/loss"]] == [2, 4]


def test_without_the_package_the_flag_is_a_usage_error(tiny_scene, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # the import fails as when it is not installed
    run = tmp_path / "run"
    code = main(["train", str(tiny_scene), "--out", str(run), "--iterations", "4", "--backend", "reference",
                 "--threads", "1", "--no-lpips", "--quiet", "--tensorboard", str(tmp_path / "board")])
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and "pip install tensorboard" in err and "--tensorboard" in err
    assert not run.exists() and not (tmp_path / "board").exists()  # before any training work


def test_a_resumed_run_writes_on_without_drawing_steps_twice(fast_config, tmp_path):
    from esgs.core.train.checkpoint import list_checkpoints

    board = tmp_path / "board"
    train(fast_config(iterations=12, checkpoint_every=5, keep_checkpoints=5, evaluate=False, tensorboard=board))
    checkpoints = dict(list_checkpoints(fast_config().out / "checkpoints"))
    assert sorted(checkpoints) == [5, 10, 12]
    checkpoints[12].unlink()  # as if the first session had been killed after step 12's report
    first = dict(_scalars(board)["train/loss"])
    train(fast_config(iterations=12, checkpoint_every=5, keep_checkpoints=5, evaluate=False, tensorboard=board,
                      resume=True))
    steps = [step for step, _ in _scalars(board)["train/loss"]]
    assert steps == [5, 10, 12]  # step 12 of the first session hidden, the resumed session's shown
    assert dict(_scalars(board)["train/loss"])[10] == first[10]
