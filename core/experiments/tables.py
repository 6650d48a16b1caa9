"""Tables of experiment results: mean and standard deviation over seeds, Markdown and JSON."""
from __future__ import annotations

import math
from typing import Any, Iterable, Optional, Sequence

#: (key in a run summary, column title, decimals)
QUALITY_COLUMNS = (("ssim", "SSIM", 4), ("psnr", "PSNR (dB)", 2), ("lpips", "LPIPS", 4),
                   ("distance_mean", "dist. mean", 4), ("distance_std", "dist. std", 4))
COST_COLUMNS = (("train_s", "train (s)", 1), ("peak_memory_mib", "peak RSS (MiB)", 0),
                ("render_s_per_frame", "render (ms/frame)", 1))


def mean_std(values: Iterable[Optional[float]]) -> dict[str, Optional[float]]:
    """{"mean", "std" (population, 0 for one value), "n"} of the non-missing values."""
    present = [float(v) for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    if not present:
        return {"mean": None, "std": None, "n": 0}
    mean = sum(present) / len(present)
    std = math.sqrt(sum((v - mean) ** 2 for v in present) / len(present))
    return {"mean": mean, "std": std, "n": len(present)}


def aggregate(summaries: Sequence[dict], keys: Sequence[str], group_by: Sequence[str] = ("variant",)) -> list[dict]:
    """One row per group (in first-seen order): the group's labels, ``seeds`` and mean/std per key."""
    groups: dict[tuple, list[dict]] = {}
    for summary in summaries:
        groups.setdefault(tuple(summary.get(name) for name in group_by), []).append(summary)
    rows = []
    for labels, members in groups.items():
        row: dict[str, Any] = dict(zip(group_by, labels))
        row["seeds"] = sorted(member.get("seed") for member in members)
        for key in keys:
            row[key] = mean_std(member.get(key) for member in members)
        rows.append(row)
    return rows


def format_cell(stats: dict, decimals: int, scale: float = 1.0) -> str:
    if stats.get("mean") is None:
        return "n/a"
    mean, std = stats["mean"] * scale, stats["std"] * scale
    return f"{mean:.{decimals}f}" if stats["n"] < 2 else f"{mean:.{decimals}f} ± {std:.{decimals}f}"


def markdown_table(rows: Sequence[dict], columns: Sequence[tuple[str, str, int]],
                   label_columns: Sequence[tuple[str, str]] = (("variant", "method"),)) -> str:
    """A Markdown table: label columns, then ``mean ± std`` per metric column."""
    titles = [title for _, title in label_columns] + ["seeds"] + [title for _, title, _ in columns]
    lines = ["| " + " | ".join(titles) + " |", "|" + "---|" * len(titles)]
    for row in rows:
        cells = [str(row.get(key, "")) for key, _ in label_columns]
        cells.append(str(len(row.get("seeds", []))))
        for key, title, decimals in columns:
            scale = 1000.0 if key == "render_s_per_frame" else 1.0
            cells.append(format_cell(row.get(key, {}), decimals, scale))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
