"""End-to-end training on the tiny synthetic scene: learning, hooks, checkpoints, outputs."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from esgs.core.errors import ConfigError, ESGSError
from esgs.core.render.sh import SHCoefficients
from esgs.core.train import LossTerm, TrainHook, train
from esgs.core.train.checkpoint import list_checkpoints, load_checkpoint
from esgs.core.train.trainer import Trainer, TrainingDivergedError

from .conftest import train_then_checkpoint


def _train_psnr(trainer: Trainer) -> float:
    from esgs.core.train.evaluate import evaluate_model

    metrics = evaluate_model(trainer.gaussians, trainer.data, backend=trainer.backend, background=trainer.background,
                             sh_degree=0, use_lpips=False, views=trainer.data.train)
    return metrics["psnr"]


def test_loss_decreases_and_train_psnr_rises(fast_config):
    trainer = Trainer(fast_config(iterations=60, densify=False))
    trainer.setup()
    psnr_before = _train_psnr(trainer)
    losses = [trainer.train_step(step).loss.item() for step in range(1, 61)]
    psnr_after = _train_psnr(trainer)
    assert np.mean(losses[-10:]) < 0.6 * np.mean(losses[:10])
    assert psnr_after > psnr_before + 3.0


def test_densification_grows_the_model_during_a_short_run(fast_config):
    # 60 steps: densification after step 8 until step 30, every step (scaled from 4000..15000 every 100)
    config = fast_config(iterations=60, densify_from=4000, densify_until=15000, max_gaussians=600)
    trainer = Trainer(config)
    trainer.setup()
    reports = []

    class Recorder(TrainHook):
        name = "recorder"

        def on_densify(self, trainer, report):
            reports.append(report)

    trainer.hooks.append(Recorder())
    start = len(trainer.gaussians)
    for step in range(1, 31):
        trainer.train_step(step)
        assert trainer.optimizer.state_sizes()["means"][0] == len(trainer.gaussians)
        assert trainer.strategy.state.grad_accum.shape[0] == len(trainer.gaussians)
    assert reports and len(trainer.gaussians) > start
    assert any(report.cloned + report.split > 0 for report in reports)
    assert all(len(report.source_index) == report.count_after for report in reports)


def test_run_folder_outputs(fast_config):
    from esgs.core.formats.ply import read_gaussians_ply

    config = fast_config(iterations=12, checkpoint_every=5, save_renders=True)
    events = []
    result = train(config, progress=events.append)
    run = config.out
    assert result.status == "completed" and result.step == 12
    saved = json.loads((run / "config.json").read_text())
    assert saved["iterations"] == 12 and saved["backend"] == "reference"
    # checkpoints at 5, 10 and the end; the last two kept
    assert [step for step, _ in list_checkpoints(run / "checkpoints")] == [10, 12]
    assert not list((run / "checkpoints").glob(".*"))  # no temporary files left
    ply = read_gaussians_ply(run / "point_cloud.ply")
    for name, value in (("means", ply.means), ("log_scales", ply.log_scales), ("quats", ply.quats_wxyz),
                        ("opacity_logit", ply.opacity_logit), ("sh_dc", ply.sh_dc[:, None, :]),
                        ("sh_rest", ply.sh_rest)):
        assert np.array_equal(value, result_model_param(run, name)), name
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["split"] == "test" and metrics["views_count"] == 2
    assert metrics["lpips"] is None and metrics["lpips_unavailable"]
    assert metrics["psnr"] == pytest.approx(np.mean([v["psnr"] for v in metrics["views"]]))
    assert sorted(p.name for p in (run / "renders" / "test").iterdir()) == [
        "view_000.png", "view_000_gt.png", "view_008.png", "view_008_gt.png"]
    lines = [json.loads(line) for line in (run / "events.jsonl").read_text().splitlines()]
    progress = [line for line in lines if line["kind"] == "progress" and line["stage"] == "train"]
    assert [line["step"] for line in progress] == [5, 10, 12]
    assert {"loss", "psnr", "n_gaussians", "eta_s"} <= set(progress[0]["metrics"])
    assert lines[-1]["kind"] == "done" and events[-1].kind == "done"


def result_model_param(run, name):
    from esgs.core.train.checkpoint import latest_checkpoint

    return load_checkpoint(latest_checkpoint(run / "checkpoints"))["gaussians"]["params"][name].numpy()


def test_resume_equals_uninterrupted(fast_config, tmp_path):
    full = train(fast_config(out=tmp_path / "full", iterations=16, evaluate=False, densify_from=8000))
    # the same run, stopped after 8 steps (a checkpoint every 8 steps), then resumed
    first = fast_config(out=tmp_path / "split", iterations=16, evaluate=False, densify_from=8000, checkpoint_every=8)
    train_then_checkpoint(first, 8)
    resumed = train(fast_config(out=tmp_path / "split", iterations=16, evaluate=False, densify_from=8000,
                                checkpoint_every=8, resume=True))
    assert resumed.step == 16 and resumed.n_gaussians == full.n_gaussians
    a = load_checkpoint(list_checkpoints(tmp_path / "full" / "checkpoints")[-1][1])
    b = load_checkpoint(list_checkpoints(tmp_path / "split" / "checkpoints")[-1][1])
    for name, value in a["gaussians"]["params"].items():
        assert torch.equal(value, b["gaussians"]["params"][name]), name  # bitwise on the CPU


def test_resume_refuses_changed_settings(fast_config):
    train(fast_config(iterations=4, evaluate=False, checkpoint_every=2))
    with pytest.raises(ConfigError, match="lambda_dssim"):
        train(fast_config(iterations=4, evaluate=False, resume=True, lambda_dssim=0.5))
    with pytest.raises(ConfigError, match="already holds a run"):
        train(fast_config(iterations=4, evaluate=False))


def test_checkpoint_round_trip(fast_config):
    config = fast_config(iterations=6, evaluate=False, checkpoint_every=6, densify_from=100)
    train(config)
    state = load_checkpoint(list_checkpoints(config.out / "checkpoints")[-1][1])
    restored = Trainer(fast_config(iterations=6, resume=True))
    restored.setup(state)
    assert restored.step == 6
    for name, value in state["gaussians"]["params"].items():
        assert torch.equal(restored.gaussians.params[name].detach(), value)
        exp_avg = restored.optimizer.adam.state[restored.gaussians.params[name]]["exp_avg"]
        assert exp_avg.shape == value.shape and exp_avg.abs().sum() > 0
    assert restored.sampler.state_dict()["order"] == state["sampler"]["order"]


class _NaNInjector(TrainHook):
    name = "nan"

    def __init__(self, at_step: int):
        self.at_step = at_step

    def after_backward(self, trainer, context):
        if context.step == self.at_step:
            trainer.gaussians.params["means"].grad[0, 0] = float("nan")


def test_nan_stops_with_clear_error_and_keeps_last_good_checkpoint(fast_config):
    config = fast_config(iterations=20, checkpoint_every=3, evaluate=False)
    with pytest.raises(TrainingDivergedError) as caught:
        train(config, hooks=[_NaNInjector(at_step=8)])
    message = str(caught.value)
    # caught by the next loss (the Gaussian is in view) or the periodic/pre-checkpoint scan
    assert ("not finite after step" in message or "the loss is nan at step 9" in message), message
    assert "step_000000006.pt" in message
    assert isinstance(caught.value, ESGSError)
    assert [step for step, _ in list_checkpoints(config.out / "checkpoints")] == [3, 6]
    last = load_checkpoint(list_checkpoints(config.out / "checkpoints")[-1][1])
    assert all(torch.isfinite(v).all() for v in last["gaussians"]["params"].values())
    errors = [json.loads(line) for line in (config.out / "events.jsonl").read_text().splitlines()]
    assert errors[-1]["kind"] == "error"


def test_nan_loss_is_reported(fast_config):
    class BadTerm(TrainHook):
        name = "bad"

        def setup(self, trainer):
            trainer.add_loss_term(LossTerm("broken", 1.0, lambda ctx: ctx.image.sum() * float("inf"), start_step=3))

    with pytest.raises(TrainingDivergedError, match="loss is .* at step 3"):
        train(fast_config(iterations=10, evaluate=False), hooks=[BadTerm()])


class _GainModule(TrainHook):
    """A stand-in ESGS module: a learnable colour gain (an nn.Module in the optimizer), a
    loss term that needs depth, and a record of every hook call."""

    name = "gain"

    def __init__(self):
        self.module = torch.nn.Linear(1, 1, bias=False)
        torch.nn.init.constant_(self.module.weight, 0.5)
        self.calls = {"setup": 0, "before_render": 0, "after_backward": 0, "on_densify": 0}
        self.depth_seen = []

    def setup(self, trainer):
        self.calls["setup"] += 1
        trainer.add_parameter_group("gain", self.module.parameters(), lr=0.05)
        trainer.add_loss_term(LossTerm("depth_probe", 1e-3, self.depth_probe, start_step=4, needs=frozenset({"depth"})))

    def depth_probe(self, context):
        self.depth_seen.append(context.step)
        assert context.depth is not None and context.depth.shape[-1] == 1
        return context.depth.mean() * 0.0 + 0.0 * context.image.mean()

    def before_render(self, trainer, context, params):
        self.calls["before_render"] += 1
        gain = self.module.weight.reshape(())
        params.colors = SHCoefficients(params.colors.dc * gain * 2.0, params.colors.rest)
        return params

    def after_backward(self, trainer, context):
        self.calls["after_backward"] += 1
        assert self.module.weight.grad is not None

    def on_densify(self, trainer, report):
        self.calls["on_densify"] += 1

    def state_dict(self):
        return {"module": self.module.state_dict()}

    def load_state_dict(self, state):
        self.module.load_state_dict(state["module"])


def test_hooks_parameter_groups_and_loss_terms(fast_config):
    hook = _GainModule()
    config = fast_config(iterations=8, evaluate=False, checkpoint_every=8, densify_from=2000, min_densify_interval=1)
    train(config, hooks=[hook])
    assert hook.calls["setup"] == 1 and hook.calls["before_render"] == 8 and hook.calls["after_backward"] == 8
    assert hook.calls["on_densify"] >= 1  # densification from step 1 every step (scaled)
    assert hook.depth_seen == [4, 5, 6, 7, 8]
    assert hook.module.weight.item() != 0.5  # the module's own parameter was optimised
    state = load_checkpoint(list_checkpoints(config.out / "checkpoints")[-1][1])
    assert torch.equal(state["hooks"]["gain"]["module"]["weight"], hook.module.weight.detach())
    assert "gain" in state["optimizer"]["names"]


def test_masked_pixels_still_count_in_the_photometric_loss(fast_config, tiny_scene, tmp_path):
    """Masks keep priors off the sky, never the photometric loss: with every pixel masked as sky the
    loss is the image error, the sky model learns from it and the sky-alpha term joins the loss."""
    import shutil

    from esgs.core.formats.imageio import write_png

    scene = tmp_path / "masked"
    shutil.copytree(tiny_scene, scene)
    (scene / "priors" / "gt" / "mask").mkdir(parents=True)
    for image in (scene / "images").iterdir():
        write_png(scene / "priors" / "gt" / "mask" / f"{image.stem}.png", np.zeros((24, 32), np.uint8))
    trainer = Trainer(fast_config(scene=scene, out=tmp_path / "run_masked"))
    trainer.setup()
    assert trainer.data.mask_source == "gt" and trainer.data.train[0].mask is not None
    assert "sky_alpha" in {term.name for term in trainer.loss_terms}
    before = trainer.sky.base.detach().clone()
    context = trainer.train_step(1)
    assert context.loss_values["l1"] > 0.01
    assert not torch.equal(trainer.sky.base.detach(), before)


def test_time_limit_stops_and_evaluates(fast_config):
    result = train(fast_config(iterations=10_000, max_minutes=0.02))  # 1.2 s
    assert result.status == "time_limit" and result.step < 10_000
    assert result.metrics is not None and (result.run_dir / "metrics.json").is_file()
    assert (result.run_dir / "point_cloud.ply").is_file()


def test_random_initialisation_without_points(fast_config, tmp_path):
    from esgs.core.colmap.io import read_model

    from .scene import make_scene

    scene = make_scene(tmp_path / "nopoints", views=4, with_points=False)
    assert not read_model(scene).points
    trainer = Trainer(fast_config(scene=scene, random_init_points=200, test_every=0))
    trainer.setup()
    means = trainer.gaussians.params["means"].detach().numpy()
    assert len(means) == 200
    assert np.abs(means - trainer.data.center).max() <= trainer.data.extent + 1e-6


def test_resume_skips_a_damaged_newest_checkpoint(fast_config):
    train(fast_config(iterations=4, evaluate=False, checkpoint_every=2))
    checkpoints = list_checkpoints(fast_config().out / "checkpoints")
    assert [step for step, _ in checkpoints] == [2, 4]
    checkpoints[-1][1].write_bytes(b"not a checkpoint")
    messages = []
    result = train(fast_config(iterations=4, evaluate=False, checkpoint_every=2, resume=True),
                   progress=lambda event: messages.append(event.message))
    assert result.status == "completed" and result.step == 4
    assert any("resuming from step 2" in message for message in messages)
    assert load_checkpoint(list_checkpoints(fast_config().out / "checkpoints")[-1][1])["step"] == 4


def test_a_stop_file_saves_a_checkpoint_and_ends_the_run_as_interrupted(fast_config, tmp_path):
    """The platform-independent cancel: a file appearing mid-run stops it like SIGTERM does."""
    from esgs.core.progress import ProgressEvent
    from esgs.core.train import train
    from esgs.core.train.checkpoint import list_checkpoints

    stop = tmp_path / "please_stop"
    stop.write_text("left by an earlier session")  # stale: removed at the start, must not stop this run

    def request_stop_at_step_12(event: ProgressEvent) -> None:
        if event.kind == "progress" and event.step >= 10:
            stop.write_text("")

    config = fast_config(iterations=40, stop_file=stop, progress_every=5)
    result = train(config, progress=request_stop_at_step_12)
    assert result.status == "interrupted" and 10 <= result.step < 40
    assert list_checkpoints(config.out / "checkpoints")[-1][0] == result.step
    assert not stop.exists()  # consumed, so a resume is not stopped again at once


def test_a_scene_that_cannot_be_read_leaves_no_run_folder(fast_config, tmp_path):
    from esgs.core.errors import DatasetError
    from esgs.core.train import train

    for scene in (tmp_path / "no_such_scene", tmp_path):  # missing; a folder without images/ and a model
        out = tmp_path / "run_of_nothing"
        with pytest.raises(DatasetError):
            train(fast_config(scene=scene, out=out))
        assert not out.exists()
    # the same --out then trains once the scene is right
    assert train(fast_config(out=tmp_path / "run_of_nothing", iterations=2)).status == "completed"


def test_grey_images_train_grey_gaussians(fast_config, tiny_scene, tmp_path):
    import shutil

    import numpy as np

    from esgs.core.formats.imageio import read_image, write_png
    from esgs.core.train.trainer import Trainer

    grey = tmp_path / "grey_scene"
    shutil.copytree(tiny_scene, grey)
    for path in sorted((grey / "images").iterdir()):
        image = read_image(path)[..., :3].astype(np.float64)
        write_png(path, np.repeat(image.mean(axis=-1, keepdims=True).round().astype(np.uint8), 3, axis=-1))

    def colour_spread(scene, **settings) -> float:
        trainer = Trainer(fast_config(scene=scene, out=tmp_path / f"run_{scene.name}_{len(settings)}", **settings))
        trainer.setup()
        for step in range(1, 21):
            trainer.train_step(step)
        sh = torch.cat([trainer.gaussians.params["sh_dc"], trainer.gaussians.params["sh_rest"]], dim=1)
        return float((sh - sh.mean(dim=-1, keepdim=True)).abs().max())

    assert colour_spread(grey) < 1e-6  # auto: every image is grey
    assert colour_spread(grey, grayscale="off") > 1e-4  # learning colours drifts off grey
    assert colour_spread(tiny_scene) > 1e-4  # colour images keep their colours


def test_a_step_frees_its_graph_and_the_parameters_densification_replaced(fast_config):
    """Nothing of a step outlives it: the returned context holds a detached loss and no render,
    and the parameters densification replaced are freed (the graph's leaf accumulators held
    them until the next step had rendered, a whole copy of the model at the peak)."""
    import gc
    import weakref

    trainer = Trainer(fast_config(iterations=200))
    trainer.setup()
    schedule = trainer.strategy.schedule
    step = next(s for s in range(1, 200) if schedule.is_densify_step(s))
    for number in range(1, step):
        trainer.train_step(number)
    old = {name: weakref.ref(param) for name, param in trainer.gaussians.params.items()}
    count = len(trainer.gaussians)
    context = trainer.train_step(step)
    assert len(trainer.gaussians) != count, "the step must densify for this test to say anything"
    assert context.output is None and context.loss.grad_fn is None and context.loss.item() > 0.0
    gc.disable()  # freed by reference counting alone, not by a later collection
    try:
        alive = [name for name, ref in old.items() if ref() is not None]
    finally:
        gc.enable()
    assert alive == [], f"parameters replaced by densification still alive: {alive}"


def test_a_checkpoint_shares_the_parameters_and_a_model_copy_does_not(fast_config):
    """A checkpoint's state is written at once, so it shares the parameters' memory (a clone
    was one more copy of the model at a checkpoint near the run's peak); the file is the same,
    and a model copy made from ``state_dict()`` (the export of GPDFN and Mip-Splatting) is still
    independent of training."""
    from esgs.core.train.gaussians import GaussianModel

    trainer = Trainer(fast_config(iterations=20))
    trainer.setup()
    for number in range(1, 4):
        trainer.train_step(number)
    params = trainer.gaussians.params
    state = trainer._state()["gaussians"]
    for name, param in params.items():
        assert state["params"][name].data_ptr() == param.data_ptr(), name
    path = trainer.save_checkpoint()
    saved = load_checkpoint(path)["gaussians"]["params"]
    for name, param in params.items():
        assert torch.equal(saved[name], param.detach()), name

    copied = GaussianModel.from_state_dict(trainer.gaussians.state_dict())
    before = {name: value.detach().clone() for name, value in copied.params.items()}
    trainer.train_step(4)
    for name, value in copied.params.items():
        assert value.data_ptr() != params[name].data_ptr(), name
        assert torch.equal(value.detach(), before[name]), f"the copy's {name} changed with training"
