"""Evaluation curves of training runs and the time a run takes to reach a quality.

A run trained with ``eval_every`` K writes an "eval" event to ``RUN/events.jsonl`` every K
steps and one for its end-of-run evaluation: the held-out PSNR and SSIM and ``train_s``, the
training seconds so far (evaluations off the clock). :func:`read_eval_curve` reads them as
:class:`EvalPoint`\\ s; :func:`time_to_reach` is the training time at which a curve first
reaches a target PSNR and/or SSIM, interpolated between the two evaluations around the
crossing.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple, Optional, Sequence

from ..formats.run_dir import RunDir


class EvalPoint(NamedTuple):
    """One evaluation of a run: its step, the training seconds so far, held-out PSNR and SSIM."""

    step: int
    train_s: float
    psnr: Optional[float]
    ssim: Optional[float]


def _number(value) -> Optional[float]:
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def _read_json(path: Path) -> Optional[dict]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _add(points: list[EvalPoint], point: EvalPoint) -> None:
    """Append ``point``; an evaluation at a step the curve already passed (a session resumed
    from an earlier checkpoint trains those steps again) replaces the points from that step on."""
    while points and points[-1].step >= point.step:
        points.pop()
    points.append(point)


def read_eval_curve(run_dir: str | Path) -> list[EvalPoint]:
    """The evaluation curve of a run folder, in step order: its "eval" events (events.jsonl),
    then the end-of-run evaluation (metrics.json) at the training seconds of train_result.json
    (``train_s``; ``elapsed_s`` for runs saved before it, which includes the end-of-run work)
    when the events do not hold it already. [] for a run with neither; unreadable lines are
    skipped."""
    run = RunDir(Path(run_dir))
    points: list[EvalPoint] = []
    events = run.events
    if events.is_file():
        for line in events.read_text(encoding="utf-8", errors="replace").splitlines():
            try:
                event = json.loads(line)
            except ValueError:
                continue  # a torn last line of a killed run
            if not isinstance(event, dict) or event.get("kind") != "eval":
                continue
            metrics = event.get("metrics") or {}
            train_s = _number(metrics.get("train_s"))
            if train_s is None or not isinstance(event.get("step"), int):
                continue
            _add(points, EvalPoint(event["step"], train_s, _number(metrics.get("psnr")), _number(metrics.get("ssim"))))
    metrics = _read_json(run.metrics)
    result = _read_json(run.result)
    if metrics is not None and result is not None:
        step = metrics.get("step", result.get("step"))
        train_s = _number(result.get("train_s"))
        train_s = _number(result.get("elapsed_s")) if train_s is None else train_s
        if isinstance(step, int) and train_s is not None and not (points and points[-1].step == step):
            _add(points, EvalPoint(step, train_s, _number(metrics.get("psnr")), _number(metrics.get("ssim"))))
    return points


def _first_crossing(curve: Sequence[EvalPoint], metric: str, target: float) -> Optional[float]:
    """Training seconds at which ``metric`` first reaches ``target`` (linear between evaluations)."""
    previous: Optional[tuple[float, float]] = None
    for point in sorted(curve, key=lambda p: (p.train_s, p.step)):
        value = getattr(point, metric)
        if value is None:
            continue
        if value >= target:
            if previous is None:
                return point.train_s  # the first evaluation already reaches it: no earlier point to interpolate from
            before_s, before = previous
            return before_s + (target - before) / (value - before) * (point.train_s - before_s)
        previous = (point.train_s, value)
    return None


def time_to_reach(curve: Sequence[EvalPoint], psnr: Optional[float] = None,
                  ssim: Optional[float] = None) -> Optional[float]:
    """The training seconds at which ``curve`` first reaches ``psnr`` (dB) and/or ``ssim``: the
    first evaluation at or above the target, moved back by linear interpolation to where the
    line from the evaluation before crosses it. With both targets, the later of the two times
    (each reached at least once); None when a target is never reached (or the curve is empty).
    The first evaluation of a curve has no point before it: reaching the target there counts at
    its own time."""
    if psnr is None and ssim is None:
        raise ValueError("time_to_reach needs a psnr or an ssim target")
    times = []
    for metric, target in (("psnr", psnr), ("ssim", ssim)):
        if target is None:
            continue
        seconds = _first_crossing(curve, metric, float(target))
        if seconds is None:
            return None
        times.append(seconds)
    return max(times)


#: Figures of :func:`time_to_baseline_quality` per run, aggregated per method row.
TIME_TO_QUALITY_FIGURES = ("to_psnr_s", "to_ssim_s", "to_quality_s", "ratio")


def time_to_baseline_quality(runs: Sequence[dict], baseline: str) -> dict:
    """The training seconds each run takes to reach the final held-out PSNR and SSIM of the
    baseline run on the same scene and seed.

    ``runs``: dicts with ``key`` (the method row's key), ``variant`` (its label), ``scene``,
    ``seed`` and ``curve`` (:func:`read_eval_curve`); ``baseline``: the baseline row's key. The
    target of a (scene, seed) is the last point of the baseline run's curve (its end-of-run
    evaluation), its training seconds the baseline's time. Returns ``{"runs": [...],
    "overall": [...], "per_scene": {...}, "missing_baseline": [...]}``: per run ``to_psnr_s``,
    ``to_ssim_s``, ``to_quality_s`` (both reached; :func:`time_to_reach`), ``ratio`` (that
    over the baseline's time), None when not reached, and ``points`` (evaluations on its
    curve); per method row (first-seen order) over all runs and per scene: ``runs``,
    ``reached`` (runs with ``to_quality_s``) and :func:`~.tables.mean_std` of each figure over
    the runs that reached it."""
    from .tables import mean_std

    targets = {}
    for run in runs:
        if run["key"] == baseline and run["curve"]:
            last = run["curve"][-1]
            if last.psnr is not None and last.ssim is not None:
                targets[(run["scene"], run["seed"])] = (last.psnr, last.ssim, last.train_s)
    records, missing = [], []
    for run in runs:
        target = targets.get((run["scene"], run["seed"]))
        if target is None:
            missing.append(f"{run['scene']} seed {run['seed']}")
            continue
        psnr, ssim, baseline_s = target
        curve = run["curve"]
        to_psnr, to_ssim = time_to_reach(curve, psnr=psnr), time_to_reach(curve, ssim=ssim)
        both = max(to_psnr, to_ssim) if to_psnr is not None and to_ssim is not None else None  # time_to_reach's rule
        records.append({"key": run["key"], "variant": run["variant"], "scene": run["scene"], "seed": run["seed"],
                        "points": len(curve), "target_psnr": psnr, "target_ssim": ssim, "baseline_s": baseline_s,
                        "to_psnr_s": to_psnr, "to_ssim_s": to_ssim, "to_quality_s": both,
                        "ratio": both / baseline_s if both is not None and baseline_s > 0 else None})

    def rows(members: Sequence[dict]) -> list[dict]:
        groups: dict[str, list[dict]] = {}
        for record in members:
            groups.setdefault(record["variant"], []).append(record)
        return [{"variant": variant, "runs": len(group),
                 "reached": sum(record["to_quality_s"] is not None for record in group),
                 "baseline_s": mean_std(record["baseline_s"] for record in group),
                 **{name: mean_std(record[name] for record in group) for name in TIME_TO_QUALITY_FIGURES}}
                for variant, group in groups.items()]

    scenes = list(dict.fromkeys(record["scene"] for record in records))
    return {"runs": records, "overall": rows(records),
            "per_scene": {scene: rows([r for r in records if r["scene"] == scene]) for scene in scenes},
            "missing_baseline": sorted(set(missing))}
