"""TensorBoard scalars of a training run (``esgs train ... --tensorboard DIR``).

An optional sink beside ``RUN/events.jsonl``, which stays the machine-readable record: the
trainer hands it the same numbers at the same points (every ``progress_every`` steps and the
end-of-run evaluation), and it writes them as TensorBoard scalars with
``torch.utils.tensorboard.SummaryWriter``. The ``tensorboard`` package is optional
(``pip install tensorboard``, the ``tensorboard`` extra); asking for the sink without it is a
:class:`~esgs.core.errors.ConfigError` raised before any training work.

Tags (the step is the training step, 1-based as the trainer's):

- ``train/loss``, ``train/psnr``: the smoothed training loss and PSNR of ``events.jsonl``
  (exponential moving averages, weight 0.4), ``train/n_gaussians``, ``train/s_per_step``
  (mean seconds per step since the session started);
- ``loss/total``: that step's weighted total loss; ``loss/<term>``: each loss term's
  unweighted value at that step (``l1``, ``dssim``, the methods' prior terms...);
- ``lr/<group>``: the learning rate of each optimizer group (``means``, ``sh_dc``, ...);
- ``eval/psnr``, ``eval/ssim``, ``eval/lpips``: the held-out views' means of ``metrics.json``,
  at the run's last step; with ``eval_every`` also PSNR and SSIM every K steps (the "eval"
  events of ``events.jsonl``).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Optional

from ..errors import ConfigError

#: The ``events.jsonl`` progress metrics written under ``train/`` (eta_s is left out: not a curve).
TRAIN_METRICS = ("loss", "psnr", "n_gaussians", "s_per_step")
#: The evaluation means written under ``eval/``.
EVAL_METRICS = ("psnr", "ssim", "lpips")


def summary_writer_class() -> type:
    """``torch.utils.tensorboard.SummaryWriter``; a ConfigError naming the package when missing."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError as err:
        raise ConfigError("--tensorboard needs the tensorboard package, which is not installed",
                          hint="pip install tensorboard, or train without --tensorboard") from err
    return SummaryWriter


class TensorBoardScalars:
    """Writes a run's scalars into ``log_dir`` (TensorBoard's event files).

    ``purge_step``: when a run resumes from a checkpoint at step S, pass S + 1 so the curves
    an interrupted session wrote past its last checkpoint are hidden, not drawn twice.
    """

    def __init__(self, log_dir: str | Path, *, purge_step: Optional[int] = None):
        writer_class = summary_writer_class()
        self.log_dir = Path(log_dir)
        self.writer = writer_class(log_dir=str(self.log_dir), purge_step=purge_step)

    def _scalar(self, tag: str, value: Any, step: int) -> None:
        if value is None:
            return
        value = float(value)
        if math.isfinite(value):
            self.writer.add_scalar(tag, value, global_step=step)

    def train_step(self, step: int, metrics: Mapping[str, float], *, loss: Any = None,
                   loss_terms: Optional[Mapping[str, float]] = None,
                   learning_rates: Optional[Mapping[str, float]] = None) -> None:
        """One progress report: ``metrics`` as written to events.jsonl, the step's total
        ``loss`` and unweighted ``loss_terms``, and each optimizer group's learning rate."""
        for key in TRAIN_METRICS:
            self._scalar(f"train/{key}", metrics.get(key), step)
        if loss is not None:
            self._scalar("loss/total", float(loss.detach()) if hasattr(loss, "detach") else loss, step)
        for name, value in (loss_terms or {}).items():
            self._scalar(f"loss/{name}", value, step)
        for name, value in (learning_rates or {}).items():
            self._scalar(f"lr/{name}", value, step)

    def evaluation(self, step: int, metrics: Mapping[str, Any]) -> None:
        """An evaluation's means (metrics.json at the end, every ``eval_every`` steps during the
        run); LPIPS only when it was computed."""
        for key in EVAL_METRICS:
            self._scalar(f"eval/{key}", metrics.get(key), step)

    def close(self) -> None:
        self.writer.flush()
        self.writer.close()
