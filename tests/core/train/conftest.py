"""Fixtures of the training tests: one tiny synthetic scene per session and a fast config."""
from __future__ import annotations

from pathlib import Path

import pytest

from .scene import make_scene


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """10 views of 32x24 pixels of a textured plane; PINHOLE cameras; 150 SfM points."""
    return make_scene(tmp_path_factory.mktemp("scene") / "plane")


@pytest.fixture
def fast_config(tiny_scene, tmp_path):
    """A TrainConfig for quick runs on ``tiny_scene``: the trusted reference rasterizer, one thread, no LPIPS."""
    from esgs.core.train import TrainConfig

    def build(**overrides) -> TrainConfig:
        values = dict(scene=tiny_scene, out=tmp_path / "run", iterations=30, backend="reference", threads=1, lpips=False,
                      progress_every=5, checkpoint_every=0, save_renders=False)
        values.update(overrides)
        return TrainConfig(**values)

    return build


def train_then_checkpoint(config, steps: int) -> None:
    """Train ``config`` for ``steps`` steps by hand and save a checkpoint, as an interrupted run leaves it."""
    from esgs.core.train.trainer import Trainer

    trainer = Trainer(config)
    trainer._start_run_dir(None)
    trainer.setup()
    for step in range(1, steps + 1):
        trainer.train_step(step)
    trainer.save_checkpoint()
