"""How accurate are label maps? AbsRel and delta1 against a scene's ground truth.

On synthetic scenes ``priors/gt`` holds the exact depth; labels are compared with it on
the pixels where both exist (the truth's surface and the label's mask):

- AbsRel = mean(|label - truth| / truth);
- delta1 = fraction of pixels with max(label / truth, truth / label) < 1.25;
- coverage = fraction of the truth's surface pixels that have a label (rendered or filled),

over all pixels of all views pooled, per view, and by range (bins of the true depth at its
25th, 50th, 75th and 90th percentiles: stereo loses accuracy with distance). The same
figures for the filled pixels alone show what hole filling adds. A trivial baseline for context: every pixel labelled
with the median true depth of its view (``baseline_*``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DatasetError
from ..formats.scene_dir import PriorSource, SceneDir

DELTA1 = 1.25


def depth_errors(label: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """AbsRel and delta1 of ``label`` [N] against ``truth`` [N] (both positive)."""
    if len(truth) == 0:
        return {"abs_rel": float("nan"), "delta1": float("nan"), "pixels": 0}
    ratio = label / truth
    return {"abs_rel": float(np.mean(np.abs(label - truth) / truth)),
            "delta1": float(np.mean(np.maximum(ratio, 1.0 / ratio) < DELTA1)), "pixels": int(len(truth))}


def label_accuracy(scene_dir: str | Path, source: str = PriorSource.LABELS.value,
                   truth_source: str = PriorSource.GT.value) -> dict[str, Any]:
    """Compare ``priors/<source>`` with ``priors/<truth_source>`` for every view of the scene.

    Returns ``{"overall": {...}, "rendered": {...}, "filled": {...}, "baseline": {...},
    "coverage": float, "views": [{"image", "abs_rel", "delta1", "coverage"}, ...]}``.
    """
    from ..formats.imageio import read_depth_exr, read_image

    scene_dir = Path(scene_dir)
    folder = SceneDir(scene_dir)
    label_root, truth_root = folder.prior(source), folder.prior(truth_source)
    for root in (label_root, truth_root):
        if not (root / "depth").is_dir():
            raise DatasetError(f"no depth maps under {root}", path=root,
                               hint="the accuracy report needs a synthetic scene (priors/gt) and its labels")
    pooled: dict[str, list[np.ndarray]] = {"label": [], "truth": [], "filled": [], "baseline": [], "surface": []}
    views = []
    covered_total = surface_total = 0
    for truth_path in sorted((truth_root / "depth").rglob("*.exr")):
        stem = str(truth_path.relative_to(truth_root / "depth").with_suffix(""))
        label_path = folder.depth_map(source, f"{stem}.exr")  # the name with a suffix: stems may hold dots
        if not label_path.is_file():
            raise DatasetError(f"no label for view {stem!r}", path=label_path)
        truth, _ = read_depth_exr(truth_path)
        label, _ = read_depth_exr(label_path)
        mask_path = folder.mask_map(source, f"{stem}.png")
        mask = read_image(mask_path) if mask_path.is_file() else np.where(label > 0, 255, 0).astype(np.uint8)
        truth_mask_path = folder.mask_map(truth_source, f"{stem}.png")
        surface = truth > 0
        if truth_mask_path.is_file():
            surface &= read_image(truth_mask_path) > 127
        labelled = (mask > 0) & (label > 0)
        both = surface & labelled
        pooled["label"].append(label[both])
        pooled["truth"].append(truth[both])
        pooled["filled"].append((mask[both] > 0) & (mask[both] < 255))
        pooled["surface"].append(truth[surface])
        pooled["baseline"].append(np.full(int(surface.sum()), np.median(truth[surface]) if surface.any() else 1.0))
        covered_total += int(both.sum())
        surface_total += int(surface.sum())
        errors = depth_errors(label[both].astype(np.float64), truth[both].astype(np.float64))
        views.append({"image": stem, **errors, "coverage": float(both.sum() / max(surface.sum(), 1))})
    if not views:
        raise DatasetError("no ground-truth depth maps found", path=truth_root / "depth")
    label_all = np.concatenate(pooled["label"]).astype(np.float64)
    truth_all = np.concatenate(pooled["truth"]).astype(np.float64)
    filled_all = np.concatenate(pooled["filled"])
    baseline_truth = np.concatenate(pooled["surface"]).astype(np.float64)
    baseline = np.concatenate(pooled["baseline"]).astype(np.float64)
    edges = np.percentile(truth_all, [0, 25, 50, 75, 90, 100]) if len(truth_all) else np.zeros(6)
    by_depth = []
    for low, high in zip(edges[:-1], edges[1:]):
        inside = (truth_all >= low) & (truth_all <= high)
        by_depth.append({"min_depth": float(low), "max_depth": float(high),
                         **depth_errors(label_all[inside], truth_all[inside])})
    return {
        "source": source, "truth": truth_source, "by_depth": by_depth,
        "overall": depth_errors(label_all, truth_all),
        "rendered": depth_errors(label_all[~filled_all], truth_all[~filled_all]),
        "filled": depth_errors(label_all[filled_all], truth_all[filled_all]),
        "coverage": covered_total / max(surface_total, 1),
        "baseline_median_depth": depth_errors(baseline, baseline_truth),
        "views": views,
    }


def format_accuracy_table(report: dict[str, Any]) -> str:
    """A plain-text table of a :func:`label_accuracy` report."""
    lines = [f"{'pixels':<24}{'AbsRel':>10}{'delta1':>10}{'count':>12}"]
    rows = [("labels (all)", report["overall"]), ("  rendered", report["rendered"]), ("  filled", report["filled"])]
    rows += [(f"  depth {row['min_depth']:.3g}-{row['max_depth']:.3g}", row) for row in report.get("by_depth", [])]
    rows.append(("baseline: median depth", report["baseline_median_depth"]))
    for title, row in rows:
        lines.append(f"{title:<24}{row['abs_rel']:>10.4f}{row['delta1']:>10.4f}{row['pixels']:>12d}")
    lines.append(f"coverage of the true surface: {100 * report['coverage']:.1f} %")
    return "\n".join(lines)
