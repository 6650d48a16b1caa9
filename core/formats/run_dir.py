"""Paths of a run folder (RUN/ layout of docs/training.md and DESIGN.md)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class RunDir:
    """The files of one training run under ``root``."""

    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @property
    def config(self) -> Path:
        return self.root / "config.json"

    @property
    def checkpoints(self) -> Path:
        return self.root / "checkpoints"

    @property
    def point_cloud(self) -> Path:
        return self.root / "point_cloud.ply"

    @property
    def point_cloud_iterations(self) -> Path:
        """``point_cloud/``: the 3DGS reference code's layout (formats/reference_3dgs.py)."""
        return self.root / "point_cloud"

    def point_cloud_iteration(self, step: int) -> Path:
        """``point_cloud/iteration_<step>/point_cloud.ply``: the final model where 3DGS tools look for it."""
        return self.point_cloud_iterations / f"iteration_{int(step)}" / "point_cloud.ply"

    @property
    def cameras_json(self) -> Path:
        """``cameras.json``: the 3DGS reference code's camera list (formats/reference_3dgs.py)."""
        return self.root / "cameras.json"

    @property
    def cfg_args(self) -> Path:
        """``cfg_args``: the 3DGS reference code's model parameters (SIBR's viewer reads it)."""
        return self.root / "cfg_args"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.json"

    @property
    def renders(self) -> Path:
        return self.root / "renders"

    @property
    def test_renders(self) -> Path:
        return self.renders / "test"

    def test_render(self, stem: str) -> Path:
        """``renders/test/<stem>.png``: the render of held-out view ``stem`` (its ground truth: ``<stem>_gt.png``)."""
        return self.test_renders / f"{stem}.png"

    @property
    def events(self) -> Path:
        return self.root / "events.jsonl"

    @property
    def sky(self) -> Path:
        """The run's sky model (train.sky.SkyModel as JSON); absent for runs with sky none."""
        return self.root / "sky.json"

    @property
    def result(self) -> Path:
        """Summary of the last training invocation (status, steps, timings)."""
        return self.root / "train_result.json"

    @property
    def stop_request(self) -> Path:
        """A file whose appearance asks a running trainer to save a checkpoint and stop."""
        return self.root / "STOP"

    def exists(self) -> bool:
        return self.config.is_file()

    def has_checkpoints(self) -> bool:
        """Whether ``checkpoints/`` exists (a run that can resume)."""
        return self.checkpoints.is_dir()
