"""The acceptance study of ESGS (issue #6): 3DGS against full ESGS on sparse-view scenes.

Every scene is a synthetic (or mesh-rendered) scene whose sparse points were triangulated
from its own images (:mod:`.sfm_scene`), so both the initial Gaussians and the ``sfm``
priors come from real feature matching, not from the exact surface points of the export.
Methods, at equal step counts and the same seeds:

- ``3DGS``: the baseline;
- ``ESGS (<source>)``: full ESGS as :func:`~esgs.core.methods.full_esgs` defines it for the
  source: depth + normal prior losses (those the source has) + GPDFN with K = 3, and with
  ``auto`` also Gaussians seeded from the depth prior (``prior_points``); for every prior
  source of the scene (auto, sfm, ndn, labels) and ``gt`` as the upper bound.

:func:`verdict` applies the issue's criteria to ESGS with each non-gt source against 3DGS:
higher SSIM, lower LPIPS and a mean Gaussian-to-mesh distance at least 20 % lower, each
"beyond the seed-to-seed spread": the difference of the means must exceed the sum of the
two standard deviations over seeds. PSNR is reported with the same spread test, as
information.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

from ..config import config_to_dict
from ..methods import full_esgs
from ..formats.scene_dir import SceneDir
from .runs import RunTask
from .tables import QUALITY_COLUMNS, aggregate

#: Prior sources in table order: auto (the default, fused from the next three) first, gt last (the upper bound).
SOURCES = ("auto", "sfm", "ndn", "labels", "gt")
#: ESGS's mean distance must be at most this fraction of 3DGS's (20 % lower).
DISTANCE_RATIO = 0.8


@dataclass(frozen=True)
class Method:
    """One row of the study: ``key`` names its run folder, ``esgs`` its ESGSConfig values."""

    label: str
    key: str
    esgs: tuple = ()
    source: str = ""


def scene_methods(scene: Path, sources: Sequence[str] = SOURCES, esgs_options: Optional[dict] = None) -> list[Method]:
    """3DGS, then full ESGS with each of ``sources`` found under ``scene/priors`` (depth and/or normal);
    ``esgs_options`` (ESGSConfig fields, e.g. ``{"depth_weight": 3.0}``) are set on every ESGS row."""
    methods = [Method("3DGS", "3dgs")]
    for source in sources:
        kinds = {kind for kind in ("depth", "normal") if SceneDir(scene).has_prior_maps(source, kind)}
        if not kinds:
            continue
        esgs = config_to_dict(full_esgs(source, scene=Path(scene), **(esgs_options or {})))
        methods.append(Method(f"ESGS ({source})", f"esgs-{source}", tuple(sorted(esgs.items())), source))
    return methods


def plan_runs(scenes: dict[str, Path], out: Path, *, iterations: int, seeds: Sequence[int],
              train: Optional[dict] = None, sources: Sequence[str] = SOURCES,
              esgs_options: Optional[dict] = None) -> list[RunTask]:
    """Run tasks ordered seed first, so a study stopped early has every method for its first seeds.

    ``scenes``: table name -> scene folder; runs go to ``out/runs/<scene>/<method>/seed<k>``.
    """
    tasks = []
    for seed in seeds:
        for name, scene in scenes.items():
            mesh = SceneDir(scene).ground_truth_mesh
            for method in scene_methods(scene, sources, esgs_options):
                config = {**(train or {}), "iterations": iterations, "seed": seed,
                          "method": "esgs" if method.esgs else "3dgs", "method_config": dict(method.esgs) or None}
                tasks.append(RunTask(name=f"{name}/{method.key}/seed{seed}", scene=Path(scene),
                                     out=Path(out) / "runs" / name / method.key / f"seed{seed}", config=config,
                                     variant=method.label, seed=seed, scene_name=name,
                                     mesh=mesh if mesh.is_file() else None, measure_render=False))
    return tasks


def scene_rows(summaries: Sequence[dict]) -> dict[str, list[dict]]:
    """Per scene, one row per method: mean/std over seeds of the quality figures (+ n_gaussians, train_s
    and steps: the steps trained, which differ between methods at equal training time)."""
    keys = [key for key, _, _ in QUALITY_COLUMNS] + ["n_gaussians", "train_s", "steps"]
    rows: dict[str, list[dict]] = {}
    for row in aggregate(summaries, keys, group_by=("scene", "variant")):
        rows.setdefault(row["scene"], []).append(row)
    return rows


def _beyond_spread(better: dict, worse: dict) -> Optional[bool]:
    """True when mean(better) > mean(worse) by more than std(better) + std(worse); None without data."""
    if better.get("mean") is None or worse.get("mean") is None:
        return None
    return better["mean"] - worse["mean"] > better["std"] + worse["std"]


def verdict(baseline: dict, candidate: dict) -> dict[str, Any]:
    """The issue's criteria for one candidate row against the 3DGS row of the same scene.

    Rows are :func:`scene_rows` rows. Each criterion: {"pass": bool | None, "detail": str}.
    """
    def negate(stats: dict) -> dict:
        return {**stats, "mean": None if stats.get("mean") is None else -stats["mean"]}

    result: dict[str, Any] = {}
    result["ssim"] = {"pass": _beyond_spread(candidate["ssim"], baseline["ssim"])}
    result["lpips"] = {"pass": _beyond_spread(negate(candidate["lpips"]), negate(baseline["lpips"]))}
    base, cand = baseline["distance_mean"], candidate["distance_mean"]
    if base.get("mean") is None or cand.get("mean") is None:
        result["distance"] = {"pass": None}
    else:
        # 20 % lower, and the gap to 0.8 x 3DGS larger than the spreads (scaled like the means)
        gap = DISTANCE_RATIO * base["mean"] - cand["mean"]
        result["distance"] = {"pass": gap > cand["std"] + DISTANCE_RATIO * base["std"],
                              "ratio": cand["mean"] / base["mean"] if base["mean"] else None}
    psnr_b, psnr_c = baseline["psnr"], candidate["psnr"]
    if psnr_b.get("mean") is None or psnr_c.get("mean") is None:
        result["psnr"] = {"change_db": None, "significant": None}
    else:
        change = psnr_c["mean"] - psnr_b["mean"]
        result["psnr"] = {"change_db": change, "significant": abs(change) > psnr_b["std"] + psnr_c["std"]}
    return result
