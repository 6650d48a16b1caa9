"""Full-image evaluation of the learned completion against what a scene already has.

Every surface pixel of every view counts (not only the pixels a source covers): a source that
leaves holes is scored after the filling a user would get. Rows, per evaluation set:

- ``sfm_interpolated``: the view's triangulated points, interpolated (linear, nearest outside
  their hull), normals from the interpolated depth;
- ``stereo_sfm``: no network at all: the stereo labels where they hold a value, the SfM
  interpolation elsewhere (the labels' normals, else the interpolation's);
- ``stereo_filled``: the ``auto`` prior as shipped before the completion network (stereo labels
  from ``esgs labels --reconstruct``, the shipped NDN pinned to the SfM points where labels are
  missing, SfM points), its remaining holes filled by the SfM interpolation;
- ``<weights>:none`` / ``:sfm`` / ``:sfm_stereo``: a completion network (or any NDN weights) with
  no evidence, with the SfM points, with the points and the real stereo labels;
- ``<weights>:fused``: the stereo labels where they hold a value, the network's ``sfm_stereo``
  output elsewhere (the fusion ``priors/auto`` makes); ``:fused_pinned`` the same with the
  network's depth first fitted to the labels (robust scale and shift, as the trainer aligns);
  ``:auto`` the network's output as ``priors/auto`` takes it (``fuse_view`` with today's rule:
  the labels where they are trusted, the network's depth through the gradient hole fill, its
  trust gate, the SfM floor), its remaining holes filled as in ``stereo_filled``;
  ``:auto_network_normals`` the same depth with the network's normals on every pixel (labels'
  normals nowhere): whether ``auto`` should take its normals from the network;
- ``<depth weights>+<normal weights>_normals:auto`` (``--hybrid A:B``): A's ``:auto`` depth with
  B's ``:auto`` normals, when one network's depth and another's normals are better;
  ``<A>+<B>:auto`` what ``esgs priors --method auto`` makes of that pair: A's depth with B's
  depth as the ``ndn`` source's second depth, B's ``:auto`` normals (the blend of the second
  depth is opt-in: ``--auto-variant blend:blend_second_depth=true`` adds that row).

Depth is scored after the robust scale/shift fit the trainer uses (``abs_rel``, ``delta1``) and,
for rows that are metric, without any alignment (``abs_rel_metric``, ``delta1_metric``);
normals by their mean angle and share under 11.25 degrees; the sky head by its IoU on views with
sky. Each set is summarised over all views and over its views with sky (the rover-height ones).

Scene preparation is cached under ``--work``: a copy with triangulated points
(``esgs.core.experiments.sfm_scene.make_sfm_scene``) and its ``auto`` priors (labels, shipped NDN,
fusion). The SfM evidence is the same triangulation the training shards hold
(``scene_triples(..., sfm_points=True)``).

    .venv/bin/python benchmarks/ndn_completion.py --set heldout=/work/runs/c25/data/scenes/heldout_* \\
        --set landform_mixed=... --weights completion=MODEL/checkpoints/step_N.pt --work DIR --json OUT
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # an idle OpenMP worker must not spin beside other jobs

import argparse  # noqa: E402
import glob  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

SKY_VIEW_SHARE = 0.02  # a view with at least this share of no-surface pixels is a "view with sky"


def prepare_scene(scene: Path, work: Path) -> Path:
    """The scene's copy with triangulated points and its ``auto`` priors (cached)."""
    from esgs.core.experiments.sfm_scene import make_sfm_scene
    from esgs.core.priors.auto import ensure_auto_priors

    copy = work / f"{scene.name}_sfm"
    if not copy.exists():
        make_sfm_scene(scene, copy)
    ensure_auto_priors(copy)
    return copy


def _resize_normals(normal: np.ndarray, valid: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    from esgs.core.ndn.data import resize_masked

    small, _ = resize_masked(normal, valid, *size)
    length = np.linalg.norm(small, axis=-1, keepdims=True)
    return (small / np.maximum(length, 1e-6)).transpose(2, 0, 1).astype(np.float32)


def _interpolated(sparse: np.ndarray, intrinsics: tuple[float, float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """SfM cells [h, w] -> (dense depth [h, w], normals [3, h, w]) at the working size."""
    from esgs.core.ndn.baselines import densify_sparse_depth, normals_from_depth

    height, width = sparse.shape
    rows, columns = np.nonzero(sparse > 0)
    dense = densify_sparse_depth(np.stack([columns + 0.5, rows + 0.5], axis=1), sparse[rows, columns], width, height)
    if dense is None:
        dense = np.ones((height, width), np.float32)
    return dense, normals_from_depth(dense, *intrinsics).astype(np.float32)


def scene_views(scene: Path, copy: Path, working_size: int = 128) -> dict:
    """Everything the rows need for one scene at the working size."""
    from esgs.core.colmap import read_model
    from esgs.core.ndn.data import resize_valid_depth, scene_triples
    from esgs.core.priors.io import load_prior_maps

    triples = scene_triples(scene, working_size, 4, sfm_points=True)
    width, height = triples.views.shape[-1], triples.views.shape[-2]
    model = read_model(scene, use_pycolmap=False)
    camera = next(iter(model.cameras.values()))
    full_width, full_height = triples.image_sizes[0]
    fx, fy, cx, cy = (float(v) for v in camera.params[:4])
    intrinsics = (fx * width / full_width, fy * height / full_height, cx * width / full_width, cy * height / full_height)
    stereo, stereo_normal, auto_depth, auto_normal = [], [], [], []
    for name in triples.names:
        labels = load_prior_maps(copy, "labels", name, size=(full_width, full_height))
        valid = labels.mask & (labels.depth > 0)
        stereo.append(resize_valid_depth(labels.depth, valid, width, height))
        stereo_normal.append(_resize_normals(labels.normal, valid, (width, height)) if labels.normal is not None
                             else np.zeros((3, height, width), np.float32))
        fused = load_prior_maps(copy, "auto", name, size=(full_width, full_height))
        valid = fused.mask & (fused.depth > 0)
        auto_depth.append(resize_valid_depth(fused.depth, valid, width, height))
        normal = fused.normal if fused.normal is not None else np.zeros((full_height, full_width, 3), np.float32)
        has_normal = valid & (np.linalg.norm(normal, axis=-1) > 0.5)
        auto_normal.append(np.where(resize_valid_depth(np.ones_like(fused.depth), has_normal, width, height)[None] > 0,
                                    _resize_normals(normal, has_normal, (width, height)), 0.0))
    interpolated = [_interpolated(sparse, intrinsics) for sparse in triples.sfm_depth]  # once per view: rows share it
    return {"names": triples.names, "views": triples.views, "depth": triples.depth, "normal": triples.normal,
            "mask": triples.mask, "sfm_depth": triples.sfm_depth, "stereo_depth": np.stack(stereo),
            "sfm_dense": np.stack([dense for dense, _ in interpolated]),
            "sfm_dense_normal": np.stack([normals for _, normals in interpolated]),
            "stereo_normal": np.stack(stereo_normal),
            "auto_depth": np.stack(auto_depth), "auto_normal": np.stack(auto_normal), "intrinsics": intrinsics}


def stereo_filled_depth(data: dict, index: int, dense: np.ndarray) -> np.ndarray:
    """Today's fill of view ``index``: the ``auto`` prior made with the shipped NDN, and the SfM
    interpolation ``dense`` where it has no value."""
    return np.where(data["auto_depth"][index] > 0, data["auto_depth"][index], dense)


def full_scores(depth: np.ndarray, normal: np.ndarray, data: dict, index: int) -> dict:
    """Aligned and metric depth scores and normal scores of view ``index``'s maps against its truth."""
    from esgs.core.ndn.infer import metric_depth_scores, score_view

    truth_depth, truth_normal, surface = data["depth"][index], data["normal"][index], data["mask"][index]
    return {**score_view(depth, normal, truth_depth, truth_normal, surface),
            **metric_depth_scores(depth, truth_depth, surface)}


def baseline_rows(data: dict) -> dict[str, list[dict]]:
    """Scores of the rows that need no network, per view."""
    rows: dict[str, list[dict]] = {"sfm_interpolated": [], "stereo_sfm": [], "stereo_filled": []}
    for index in range(len(data["names"])):
        surface = data["mask"][index]
        dense, normals = data["sfm_dense"][index], data["sfm_dense_normal"][index]
        rows["sfm_interpolated"].append(full_scores(dense, normals, data, index))
        stereo, stereo_normal = data["stereo_depth"][index], data["stereo_normal"][index]
        has_stereo_normal = (stereo > 0) & (np.linalg.norm(stereo_normal, axis=0) > 0.5)
        rows["stereo_sfm"].append(full_scores(np.where(stereo > 0, stereo, dense),
                                              np.where(has_stereo_normal[None], stereo_normal, normals), data, index))
        fused = data["auto_depth"][index]
        filled = stereo_filled_depth(data, index, dense)
        fused_normal = data["auto_normal"][index]
        normal = np.where(np.linalg.norm(fused_normal, axis=0, keepdims=True) > 0.5, fused_normal, normals)
        rows["stereo_filled"].append({**full_scores(filled, normal, data, index),
                                      "hole_share": float(((fused <= 0) & surface).sum() / max(surface.sum(), 1))})
    return rows


def network_rows(name: str, weights: Path, data: dict, modes: list[str], steps: int | None,
                 ensemble: int | None, auto_maps: dict | None = None,
                 variants: dict[str, Any] | None = None) -> dict[str, list[dict]]:
    """Scores of one set of weights under each evidence mode, per view (with CPU seconds per view).

    With the stereo mode, a ``<name>:fused`` row too: the stereo labels (depth and normals) where
    they are valid, the network's metric output elsewhere (what ``priors/auto`` does with them),
    and ``:fused_pinned``, the same with the network's depth first fitted to the labels. The
    ``:auto`` maps (depth, normals) of each view are appended to ``auto_maps[name]`` when given.
    ``variants`` (name -> ``AutoPriorSettings``): a ``:auto[name]`` row per entry, the same
    output fused with those settings instead of the defaults.
    """
    from esgs.core.ndn.checkpoint import load_checkpoint
    from esgs.core.ndn.infer import pin_to_labels, predict_triple, score_triple

    model, diffusion, config, _ = load_checkpoint(weights)
    rows: dict[str, list[dict]] = {}
    for mode in modes if config.model.evidence else ["none"]:
        for index in range(len(data["names"])):
            started = time.process_time()
            depth, normal, sky, metric = predict_triple(model, diffusion, data, index, steps=steps, seed=index,
                                                        ensemble=ensemble, evidence_mode=mode)
            seconds = time.process_time() - started
            rows.setdefault(f"{name}:{mode}", []).append(
                {**score_triple(depth, normal, sky, metric, data, index), "cpu_s_per_view": seconds})
            if mode == "sfm_stereo" and metric:
                stereo = data["stereo_depth"][index]
                stereo_normal = data["stereo_normal"][index]
                has_normal = (stereo > 0) & (np.linalg.norm(stereo_normal, axis=0) > 0.5)
                fused_normal = np.where(has_normal[None], stereo_normal, normal)
                for row, filler in (("fused", depth), ("fused_pinned", pin_to_labels(depth, stereo))):
                    fused = np.where(stereo > 0, stereo, filler)
                    rows.setdefault(f"{name}:{row}", []).append(
                        full_scores(fused, fused_normal, data, index))
            if (mode == "sfm_stereo" and metric) or not config.model.evidence:
                # what priors/auto makes of these weights: metric output fitted to the labels, or
                # a relative one that the fusion pins to the SfM points itself
                guide = pin_to_labels(depth, data["stereo_depth"][index]) if metric else depth
                filled, filled_normal, report = auto_fused(data, index, guide, normal, relative=not metric)
                if auto_maps is not None:
                    auto_maps.setdefault(name, []).append((filled, filled_normal, guide, not metric))
                rows.setdefault(f"{name}:auto", []).append(
                    {**full_scores(filled, filled_normal, data, index),
                     "ndn_trust": report.get("ndn", {}).get("trust", 0.0),
                     "fill_gradient": float((report.get("fill") or {}).get("used") == "gradient")})
                for variant, settings in (variants or {}).items():
                    other, other_normal, _ = auto_fused(data, index, guide, normal, relative=not metric,
                                                        settings=settings)
                    rows.setdefault(f"{name}:auto[{variant}]", []).append(full_scores(other, other_normal, data, index))
                # the same depth with the network's normals on every pixel it has one: whether
                # auto should take its normals from the network rather than from the labels
                has_network_normal = np.linalg.norm(normal, axis=0, keepdims=True) > 0.5
                network_normal = np.where(has_network_normal, normal, filled_normal)
                rows.setdefault(f"{name}:auto_network_normals", []).append(
                    full_scores(filled, network_normal, data, index))
    return rows


def auto_fused(data: dict, index: int, network_depth: np.ndarray, network_normal: np.ndarray, *,
               relative: bool = False, settings: Any = None, second_depth: np.ndarray | None = None,
               second_relative: bool = False) -> tuple[np.ndarray, np.ndarray, dict]:
    """View ``index`` fused by ``priors.auto.fuse_view`` (its default settings) at the working
    size, with the network's depth (as ``esgs priors --method ndn`` writes it: metric and fitted to
    the labels, or ``relative``, then pinned to the SfM points by the fusion) and normals in the NDN slot, the real stereo labels, the SfM cells and the true
    sky (the synthetic scenes' ``auto`` takes its sky from ``gt``); the pixels it leaves empty
    take the SfM interpolation as in ``stereo_filled``. ``second_depth``: another network's depth
    as the ``ndn`` source's second depth. Returns (depth, normals [3, h, w], the fusion's report)."""
    from esgs.core.priors.auto import fuse_view
    from esgs.core.priors.io import PriorMaps

    stereo = data["stereo_depth"][index]
    stereo_normal = data["stereo_normal"][index].transpose(1, 2, 0)
    surface = data["mask"][index]
    labels = PriorMaps(depth=stereo, normal=stereo_normal, mask=stereo > 0, source="labels")
    ndn = PriorMaps(depth=network_depth.astype(np.float32), normal=network_normal.transpose(1, 2, 0),
                    mask=network_depth > 0, relative_depth=relative, source="ndn",
                    second_depth=None if second_depth is None else second_depth.astype(np.float32),
                    second_relative_depth=second_relative)
    fx, fy, cx, cy = data["intrinsics"]
    camera = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    fused = fuse_view(data["sfm_depth"][index], labels, ndn, ~surface, settings, intrinsics=camera)
    dense, dense_normals = data["sfm_dense"][index], data["sfm_dense_normal"][index]
    has_normal = fused.mask & (np.linalg.norm(fused.normal, axis=-1) > 0.5)
    depth = np.where(fused.depth > 0, fused.depth, dense)
    normal = np.where(has_normal[None], fused.normal.transpose(2, 0, 1), dense_normals)
    return depth, normal, fused.report


def hybrid_rows(data: dict, depth_maps: list, normal_maps: list) -> list[dict]:
    """Per view: the ``:auto`` depth of one network with the ``:auto`` normals of another (the
    labels' normals where the labels hold, each network's in the holes it fills)."""
    rows = []
    for index, ((depth, *_), (_, normal, *_)) in enumerate(zip(depth_maps, normal_maps)):
        rows.append(full_scores(depth, normal, data, index))
    return rows


def shipped_pair_rows(data: dict, depth_maps: list, normal_maps: list, settings: Any = None) -> list[dict]:
    """Per view: the pair as ``priors/auto`` fuses it today (or with ``settings``): the first
    network's depth with the second's as the ``ndn`` source's second depth, the second's
    ``:auto`` normals."""
    rows = []
    for index, ((_, _, guide, relative), (_, normal, second, second_relative)) in enumerate(zip(depth_maps,
                                                                                                normal_maps)):
        depth, _, report = auto_fused(data, index, guide, normal, relative=relative, settings=settings,
                                      second_depth=second, second_relative=second_relative)
        rows.append({**full_scores(depth, normal, data, index),
                     "blend_share": float((report.get("blend") or {}).get("share", 0.0)),
                     "second_alone": float(report.get("ndn", {}).get("from") == "second depth")})
    return rows


def parse_variant(text: str) -> tuple[str, Any]:
    """``NAME:FIELD=VALUE[,FIELD=VALUE]`` -> (NAME, ``AutoPriorSettings`` with those fields, typed
    as their defaults)."""
    from dataclasses import replace

    from esgs.core.priors.auto import AutoPriorSettings

    name, _, assignments = text.partition(":")
    defaults = AutoPriorSettings()
    changes: dict[str, Any] = {}
    for assignment in filter(None, assignments.split(",")):
        key, _, value = assignment.partition("=")
        if not hasattr(defaults, key):
            raise SystemExit(f"--auto-variant {text!r}: AutoPriorSettings has no field {key!r}")
        kind = type(getattr(defaults, key))
        changes[key] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    settings = replace(defaults, **changes)
    settings.validate()
    return name, settings


def summarise(per_view: list[dict], sky_views: list[bool]) -> dict:
    from esgs.core.ndn.infer import mean_scores

    chosen = [s for s, sky in zip(per_view, sky_views) if sky]
    return {"views": len(per_view), "all": mean_scores(per_view),
            "views_with_sky": {"views": len(chosen), **mean_scores(chosen)} if chosen else None}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--set", action="append", required=True, metavar="NAME=GLOB[,GLOB]",
                        help="an evaluation set: scene folders (globs)")
    parser.add_argument("--weights", action="append", default=[], metavar="NAME=PATH", help="network weights to score")
    parser.add_argument("--modes", nargs="+", default=["none", "sfm", "sfm_stereo"], help="evidence modes")
    parser.add_argument("--steps", type=int, default=None, help="DDIM steps of diffusion weights (default: theirs)")
    parser.add_argument("--ensemble", type=int, default=None, help="samples per view of diffusion weights")
    parser.add_argument("--work", type=Path, required=True, help="cache of prepared scene copies")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--hybrid", action="append", default=[], metavar="DEPTH:NORMALS",
                        help="a row with one weights' :auto depth and another's :auto normals (names from --weights)")
    parser.add_argument("--auto-variant", action="append", default=[], metavar="NAME:FIELD=VALUE[,FIELD=VALUE]",
                        help="also a :auto[NAME] row fused with these AutoPriorSettings fields changed")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    variants = dict(parse_variant(text) for text in args.auto_variant)
    args.work.mkdir(parents=True, exist_ok=True)
    weights = [(text.partition("=")[0], Path(text.partition("=")[2])) for text in args.weights]
    hybrids = [tuple(text.split(":")) for text in args.hybrid]
    known = {name for name, _ in weights}
    for pair in hybrids:
        if len(pair) != 2 or not set(pair) <= known:
            parser.error(f"--hybrid takes DEPTH_WEIGHTS:NORMAL_WEIGHTS, two names given with --weights ({sorted(known)})")
    result: dict = {"what": "full-image scores of the learned completion against SfM and stereo labels with "
                            "today's hole filling (benchmarks/ndn_completion.py)",
                    "command": " ".join([Path(sys.executable).name, *sys.argv]), "machine": platform.node(),
                    "weights": {name: str(path) for name, path in weights}, "sets": {}}
    for text in args.set:
        set_name, _, patterns = text.partition("=")
        scenes = sorted(Path(p) for pattern in patterns.split(",") for p in glob.glob(pattern))
        per_row: dict[str, list[dict]] = {}
        sky_views: list[bool] = []
        view_names: list[str] = []
        for scene in scenes:
            print(f"[{set_name}] {scene.name}", flush=True)
            copy = prepare_scene(scene, args.work)
            data = scene_views(scene, copy)
            sky_views += [float((~mask).mean()) >= SKY_VIEW_SHARE for mask in data["mask"]]
            view_names += [f"{scene.name}/{name}" for name in data["names"]]
            rows = baseline_rows(data)
            auto_maps: dict[str, list] = {}
            for name, path in weights:
                rows.update(network_rows(name, path, data, args.modes, args.steps, args.ensemble, auto_maps, variants))
            for depth_name, normal_name in hybrids:
                missing = {depth_name, normal_name} - set(auto_maps)
                if missing:  # an evidence network makes its :auto row only in the sfm_stereo mode
                    parser.error(f"--hybrid: no :auto row for {sorted(missing)}; add sfm_stereo to --modes")
                rows[f"{depth_name}+{normal_name}_normals:auto"] = hybrid_rows(data, auto_maps[depth_name],
                                                                                auto_maps[normal_name])
                rows[f"{depth_name}+{normal_name}:auto"] = shipped_pair_rows(data, auto_maps[depth_name],
                                                                             auto_maps[normal_name])
                for variant, settings in variants.items():
                    rows[f"{depth_name}+{normal_name}:auto[{variant}]"] = shipped_pair_rows(
                        data, auto_maps[depth_name], auto_maps[normal_name], settings)
            for row, scores in rows.items():
                per_row.setdefault(row, []).extend(scores)
        result["sets"][set_name] = {"scenes": [str(s) for s in scenes], "views": view_names,
                                    "rows": {row: summarise(scores, sky_views) for row, scores in per_row.items()},
                                    "per_view": per_row}
        from esgs.core.io_utils import atomic_write_json

        atomic_write_json(args.json, result)  # after every set: a long run keeps what it has
        for row, summary in result["sets"][set_name]["rows"].items():
            a = summary["all"]
            print(f"  {row:32s} AbsRel {a['abs_rel']:.4f} d1 {a['delta1']:.3f} normals {a['normal_mean_deg']:.1f} "
                  f"metric {a.get('abs_rel_metric', float('nan')):.4f} sky {a.get('sky_iou', float('nan')):.3f}",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
