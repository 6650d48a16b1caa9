"""Each method against a baseline on the same scene and seed: paired differences over runs.

A table of means over scenes and seeds mixes two spreads: how much scenes differ from one
another and how much a method differs from the baseline. What a reader of a comparison
wants is the second: on each (scene, seed) both rows ran, how much better or worse is the
method, and is that more than the runs disagree. :func:`paired_rows` gives, per method and
metric, the mean and standard deviation of the per-run difference (method minus baseline;
for the distance to the mesh the per-run ratio, method over baseline), how many runs came
out better, and a verdict: ``better`` or ``worse`` when the mean is on that side of "no
change" by more than one standard deviation of the per-run values (beyond the spread),
else ``within`` the spread (always for a single run). A run whose figure or the baseline's
is missing or not finite, or whose baseline distance is 0, is left out of that metric (its
``n`` says how many counted).
"""
from __future__ import annotations

import math
from typing import Any, Optional, Sequence

from .tables import mean_std

#: (key in a run summary, column title, decimals, how the method is compared): ``higher`` or
#: ``lower`` is better for a difference; ``ratio`` (lower is better) divides by the baseline.
PAIRED_COLUMNS = (("ssim", "SSIM", 4, "higher"), ("psnr", "PSNR (dB)", 2, "higher"), ("lpips", "LPIPS", 4, "lower"),
                  ("distance_mean", "distance (x)", 3, "ratio"))


def _paired_value(value: Optional[float], base: Optional[float], kind: str) -> Optional[float]:
    """The run's difference (or ratio) against the baseline's run; None when either is
    missing or not finite (PSNR of identical images is infinite) or a ratio's baseline is 0."""
    if value is None or base is None or not (math.isfinite(float(value)) and math.isfinite(float(base))):
        return None
    if kind == "ratio":
        return float(value) / float(base) if float(base) > 0 else None
    return float(value) - float(base)


def _is_better(change: float, kind: str) -> bool:
    return change > 0 if kind == "higher" else change < 1.0 if kind == "ratio" else change < 0


def _verdict(stats: dict, kind: str) -> Optional[str]:
    """``better`` / ``worse`` when the mean is beyond one std of the per-run values from no
    change; one run has no spread to be beyond (``within``)."""
    if not stats["n"]:
        return None
    if stats["n"] < 2:
        return "within"
    gain = stats["mean"] - (1.0 if kind == "ratio" else 0.0)
    if kind != "higher":
        gain = -gain
    if abs(gain) <= stats["std"] or gain == 0:
        return "within"
    return "better" if gain > 0 else "worse"


def paired_rows(runs: Sequence[dict], baseline: str,
                columns: Sequence[tuple[str, str, int, str]] = PAIRED_COLUMNS) -> list[dict]:
    """One row per method (``variant``) other than ``baseline``, in first-seen order.

    ``runs``: run summaries with ``variant``, ``scene``, ``seed`` and the metrics. A run is
    paired with the baseline's run of the same scene and seed; runs without one are left
    out (``runs`` counts the pairs). Per metric key: ``mean``, ``std``, ``n`` of the per-run
    differences (ratios for ``ratio`` columns), ``better`` (runs in which the method did
    better) and ``verdict`` (:func:`_verdict`; None without a value)."""
    base = {(run.get("scene"), run.get("seed")): run for run in runs if run.get("variant") == baseline}
    grouped: dict[Any, list[tuple[dict, dict]]] = {}
    for run in runs:
        pair = base.get((run.get("scene"), run.get("seed")))
        if run.get("variant") != baseline and pair is not None:
            grouped.setdefault(run.get("variant"), []).append((run, pair))
    rows = []
    for variant, pairs in grouped.items():
        row: dict[str, Any] = {"variant": variant, "baseline": baseline, "runs": len(pairs)}
        for key, _, _, kind in columns:
            changes = [_paired_value(run.get(key), pair.get(key), kind) for run, pair in pairs]
            changes = [change for change in changes if change is not None]
            stats = mean_std(changes)
            stats["better"] = sum(_is_better(change, kind) for change in changes)
            stats["verdict"] = _verdict(stats, kind)
            row[key] = stats
        rows.append(row)
    return rows


def _paired_cell(stats: dict, decimals: int, kind: str) -> str:
    if not stats.get("n"):
        return "n/a"
    sign = "" if kind == "ratio" else "+"
    cell = f"{stats['mean']:{sign}.{decimals}f}"
    if stats["n"] > 1:
        cell += f" ± {stats['std']:.{decimals}f}"
    cell += f" ({stats['better']}/{stats['n']} better)"
    return f"**{cell}**" if stats["verdict"] == "better" else f"_{cell}_" if stats["verdict"] == "worse" else cell


def paired_markdown(rows: Sequence[dict], columns: Sequence[tuple[str, str, int, str]] = PAIRED_COLUMNS) -> str:
    """A Markdown table of :func:`paired_rows`: bold = better beyond the spread, italic = worse beyond it."""
    titles = ["method", "runs", *(f"{title}: {'ratio' if kind == 'ratio' else 'difference'}"
                                  for _, title, _, kind in columns)]
    lines = ["| " + " | ".join(titles) + " |", "|" + "---|" * len(titles)]
    for row in rows:
        cells = [str(row["variant"]), str(row["runs"])]
        cells += [_paired_cell(row[key], decimals, kind) for key, _, decimals, kind in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
