"""How ``priors/auto`` fills the stereo labels' holes, scored against the exact depth.

For each scene (a synthetic or mesh-rendered scene folder with ``priors/gt``), a copy with SfM
points triangulated from the rendered images is made and its sources computed as a user's run
would (``ensure_auto_priors``: stereo labels, shipped NDN, SfM; cached under ``--work``). Then
every view is fused again under each variant of ``AutoPriorSettings`` (``fuse_view``, the code
``priors/auto`` runs) and its depth scored against ``priors/gt``, without any alignment:

- over every surface pixel the fused map covers (``abs_rel``, ``delta1``, ``coverage``);
- over the holes only (surface pixels without a label that the fill covers: ``hole_*``);
- per view, and summarised over all views and over the views with sky.

Variants: ``pinned`` (NDN pinned to the view's SfM points, the rule before 2026-11-29) and
``gradient`` fills at each ``--reach``, ``--anchor-weight`` and ``--border-tolerance`` given.

    .venv/bin/python benchmarks/auto_hole_fill.py --work DIR --json OUT SCENE [SCENE ...]
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # an idle OpenMP worker must not spin beside other jobs

import argparse  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

SKY_VIEW_SHARE = 0.02  # a view with at least this share of no-surface pixels is a "view with sky"


def depth_scores(depth: np.ndarray, truth: np.ndarray, where: np.ndarray) -> dict:
    """Metric AbsRel and delta1 of ``depth`` against ``truth`` over ``where`` (and the pixel count)."""
    pick = where & (depth > 0) & (truth > 0)
    if not pick.any():
        return {"abs_rel": float("nan"), "delta1": float("nan"), "pixels": 0}
    d, t = depth[pick].astype(np.float64), truth[pick].astype(np.float64)
    return {"abs_rel": float(np.mean(np.abs(d - t) / t)),
            "delta1": float(np.mean(np.maximum(d / t, t / d) < 1.25)), "pixels": int(pick.sum())}


def variants(reaches: list[float], anchor_weights: list[float], tolerances: list[float], fits: list[str],
             checks: list[str], gates: tuple[str, ...] = ("on",)):
    from esgs.core.priors.auto import AutoPriorSettings

    base = AutoPriorSettings()
    yield "pinned", replace(base, hole_fill="pinned")
    if "off" in gates:
        # every view's NDN used, however far it is from the SfM points (the trust gate's counterfactual)
        yield "pinned_gateoff", replace(base, hole_fill="pinned", max_error=float("inf"))
        yield "default_gateoff", replace(base, max_error=float("inf"))
    for reach in reaches:
        for weight in anchor_weights:
            for tolerance in tolerances:
                for fit in fits:
                    for check in checks:
                        name = f"gradient_r{reach:g}_a{weight:g}_t{tolerance:g}_{fit}_check{check}"
                        yield name, replace(base, hole_fill="gradient", fill_reach=reach, fill_anchor_weight=weight,
                                            fill_border_tolerance=tolerance, fill_border_fit=fit,
                                            fill_check=check == "on")


def score_scene(copy: Path, settings_list: list[tuple[str, object]]) -> dict[str, list[dict]]:
    """Per variant, per view scores of the fused depth of the scene copy ``copy``."""
    from esgs.core.colmap import read_model
    from esgs.core.formats.scene_dir import PriorSource
    from esgs.core.priors.auto import fuse_view, view_sources
    from esgs.core.priors.io import load_prior_maps

    model = read_model(copy)
    rows: dict[str, list[dict]] = {}
    for image in model.sorted_images():
        camera = model.cameras[image.camera_id]
        size = (camera.width, camera.height)
        rotation = image.rotation_matrix()
        sfm, maps = view_sources(copy, model, image, ["labels", "ndn"])
        gt = load_prior_maps(copy, PriorSource.GT, image.name, size=size, world_to_camera_rotation=rotation)
        surface = gt.mask & (gt.depth > 0)
        sky = ~gt.mask  # the synthetic scenes' auto prior takes its sky from gt (the trainer's mask order)
        labels = maps.get(PriorSource.LABELS)
        labelled = (labels.mask & (labels.depth > 0)) if labels is not None else np.zeros_like(surface)
        for name, settings in settings_list:
            started = time.perf_counter()
            fused = fuse_view(sfm, labels, maps.get(PriorSource.NDN), sky, settings)
            seconds = time.perf_counter() - started
            hole = surface & ~labelled & fused.mask
            rows.setdefault(name, []).append({
                "view": image.name, "sky_view": bool((~gt.mask).mean() >= SKY_VIEW_SHARE),
                **depth_scores(fused.depth, gt.depth, surface),
                "coverage": float((fused.mask & surface).sum() / max(int(surface.sum()), 1)),
                **{f"hole_{k}": v for k, v in depth_scores(fused.depth, gt.depth, hole).items()},
                "hole_share": float(hole.sum() / max(int(surface.sum()), 1)), "fuse_s": seconds,
                "labels_gated": float(fused.report.get("labels", {}).get("trust", 1.0) <= 0),
                "ndn_gated": float(fused.report.get("ndn", {}).get("trust", 1.0) <= 0)})
    return rows


def summarise(views: list[dict]) -> dict:
    def mean(key: str, subset: list[dict]) -> float:
        values = [v[key] for v in subset if np.isfinite(v[key])]
        return float(np.mean(values)) if values else float("nan")

    out = {}
    for label, subset in (("all", views), ("sky_views", [v for v in views if v["sky_view"]])):
        out[label] = {key: mean(key, subset) for key in ("abs_rel", "delta1", "coverage", "hole_abs_rel",
                                                         "hole_delta1", "hole_share", "fuse_s", "labels_gated",
                                                         "ndn_gated")}
        out[label]["views"] = len(subset)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="+", type=Path, help="scene folders with priors/gt")
    parser.add_argument("--work", type=Path, required=True, help="cache of the scenes' SfM copies and their sources")
    from esgs.core.priors.auto import AutoPriorSettings

    defaults = AutoPriorSettings()
    parser.add_argument("--reach", type=float, nargs="+", default=[defaults.fill_reach],
                        help="gradient fill reaches to score (default: auto's)")
    parser.add_argument("--anchor-weight", type=float, nargs="+", default=[defaults.fill_anchor_weight],
                        help="gradient fill SfM anchor weights (default: auto's)")
    parser.add_argument("--border-tolerance", type=float, nargs="+", default=[defaults.fill_border_tolerance],
                        help="gradient fill border tolerances (0 = every border label; default: auto's)")
    parser.add_argument("--border-fit", nargs="+", default=[defaults.fill_border_fit], choices=["median", "plane"],
                        help="what border labels are checked against (default: auto's)")
    parser.add_argument("--fill-check", nargs="+", default=["on" if defaults.fill_check else "off"],
                        choices=["on", "off"], help="check the fill against the SfM points in the holes (default: auto's)")
    parser.add_argument("--ndn-gate", nargs="+", default=["on"], choices=["on", "off"],
                        help="with 'off': also the pinned and default fills with the trust gate off (max_error "
                             "infinite: every view's NDN is used, and its labels, whose gate the per-view rows' "
                             "'labels_gated' says never acted under the defaults on our scenes)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args(argv)
    import torch

    from esgs.core.experiments.sfm_scene import make_sfm_scene
    from esgs.core.io_utils import atomic_write_json
    from esgs.core.priors.auto import ensure_auto_priors

    torch.set_num_threads(args.threads)
    args.work.mkdir(parents=True, exist_ok=True)
    settings_list = list(variants(args.reach, args.anchor_weight, args.border_tolerance, args.border_fit, args.fill_check,
                                  tuple(args.ndn_gate)))
    result: dict = {"what": "priors/auto depth against the exact depth, per hole-fill variant "
                            "(benchmarks/auto_hole_fill.py)",
                    "command": " ".join([Path(sys.executable).name, *sys.argv]), "machine": platform.node(),
                    "scenes": {}, "summary": {}}
    every: dict[str, list[dict]] = {}
    for scene in args.scenes:
        copy = args.work / f"{scene.name}_sfm"
        print(f"[{scene.name}] preparing", flush=True)
        if not copy.exists():
            make_sfm_scene(scene, copy)
        ensure_auto_priors(copy)
        rows = score_scene(copy, settings_list)
        result["scenes"][scene.name] = {"scene": str(scene), "per_view": rows,
                                        "summary": {name: summarise(v) for name, v in rows.items()}}
        for name, views in rows.items():
            every.setdefault(name, []).extend(views)
            s = result["scenes"][scene.name]["summary"][name]["all"]
            print(f"  {name:24s} AbsRel {s['abs_rel']:.4f} d1 {s['delta1']:.3f} holes {s['hole_share']:.3f}: "
                  f"AbsRel {s['hole_abs_rel']:.4f} d1 {s['hole_delta1']:.3f}", flush=True)
        result["summary"] = {name: summarise(v) for name, v in every.items()}
        atomic_write_json(args.json, result)  # after every scene: a long run keeps what it has
    for name, summary in result["summary"].items():
        a, s = summary["all"], summary["sky_views"]
        print(f"{name:24s} all AbsRel {a['abs_rel']:.4f} holes {a['hole_abs_rel']:.4f} | sky views AbsRel "
              f"{s['abs_rel']:.4f} holes {s['hole_abs_rel']:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
