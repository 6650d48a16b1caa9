"""``TrainHook.view_params``: the per-view parameters of the end-of-run evaluation and of ``render_model``."""
from __future__ import annotations

from dataclasses import replace

import torch

from esgs.core.train.hooks import TrainHook
from esgs.core.train.trainer import Trainer


class _HideInOneView(TrainHook):
    """Shows the model unchanged, except in the view named ``hidden`` where every Gaussian is transparent."""

    name = "hide_in_one_view"

    def __init__(self, hidden: str):
        self.hidden = hidden
        self.seen: list[str] = []

    def view_params(self, run, view, params):
        self.seen.append(view.name)
        if view.name != self.hidden:
            return params
        return replace(params, opacities=torch.zeros_like(params.opacities))


def test_the_evaluation_renders_each_held_out_view_with_the_hooks_view_params(fast_config, tmp_path):
    config = fast_config(iterations=6, test_every=3, evaluate=True, densify_until=0, out=tmp_path / "plain")
    plain = Trainer(config).run().metrics
    hidden = plain["views"][0]["name"]
    hook = _HideInOneView(hidden)
    metrics = Trainer(replace(config, out=tmp_path / "hooked"), hooks=[hook]).run().metrics
    assert hook.seen == [row["name"] for row in plain["views"]]  # once per held-out view, in order
    rows = {row["name"]: row for row in metrics["views"]}
    assert rows[hidden]["psnr"] < plain["views"][0]["psnr"] - 1.0  # rendered as background only
    for row in plain["views"][1:]:
        assert abs(rows[row["name"]]["psnr"] - row["psnr"]) < 1e-6


def test_render_model_applies_view_params_for_the_view(fast_config, tmp_path):
    trainer = Trainer(fast_config(out=tmp_path / "run"), hooks=[_HideInOneView("nothing")])
    trainer._start_run_dir(None)
    trainer.setup()
    view = trainer.data.train[0]
    shown = trainer.render_model(view)
    hook = trainer.hooks[0]
    assert hook.seen == [view.name]
    hook.hidden = view.name
    assert float(trainer.render_model(view).alpha.max()) == 0.0 < float(shown.alpha.max())
