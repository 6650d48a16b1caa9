"""NDN against its two baselines on held-out triples (prints tables; writes JSON; not a test).

Methods (all scored by ``esgs.core.ndn.infer.score_view``: depth aligned by the robust
scale/shift fit, then AbsRel and delta1; normal mean angular error and share < 11.25 deg;
over the ground-truth surface pixels of each triple at the working resolution):

- ``ndn:<label>=CHECKPOINT``: the diffusion model (its weight average when the checkpoint has one), DDIM at
  its saved steps, seed 0 (+ triple index); ``CHECKPOINT@steps=5,ensemble=3,reduce=median`` overrides the
  saved sampling settings (an ensemble: the per-pixel median or mean of several samples);
- ``regression:<label>=CHECKPOINT``: the same network trained with ``--prediction regression``
  (one forward pass);
- ``sfm``: SIFT + exhaustive matching + triangulation with the known poses (pycolmap) on the
  scene's images (2x upscaled), each view's observed points interpolated linearly (nearest
  outside their hull); normals differentiated from that depth. Needs the rendered scene
  folders (``DATA/scenes/<split>_<preset>_<seed>``).

    .venv/bin/python benchmarks/ndn_baselines.py DATA [DATA2 ...] --method ndn:step1000=M/checkpoints/step_0001000.pt \\
        --method regression:step1000=R/checkpoints/step_0001000.pt --method sfm --json out.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
METRICS = ("abs_rel", "delta1", "normal_mean_deg", "normal_within_11_25")


def scene_shards(data_dir: Path, split: str) -> list[tuple[str, dict]]:
    """(scene name, arrays incl. names) of every shard of a split, in name order."""
    shards = []
    for path in sorted((data_dir / "shards").glob(f"{split}_*.npz")):
        with np.load(path, allow_pickle=False) as shard:
            shards.append((path.stem, {key: shard[key] for key in ("views", "depth", "normal", "mask", "names")}))
    if not shards:
        sys.exit(f"no {split} shards in {data_dir / 'shards'}")
    return shards


def score_network(checkpoint: str, shards: list[tuple[str, dict]]) -> dict[str, list[dict]]:
    """Scores of a checkpoint (its EMA weights when it has them). ``CHECKPOINT@steps=5,ensemble=3,reduce=median``
    overrides the sampling settings saved with it."""
    from esgs.core.ndn.infer import evaluate_arrays
    from esgs.core.ndn.train import load_checkpoint

    checkpoint, _, options = checkpoint.partition("@")
    model, diffusion, _, payload = load_checkpoint(checkpoint)
    names = {"steps": "sample_steps", "ensemble": "sample_ensemble", "reduce": "sample_reduce"}
    for option in filter(None, options.split(",")):
        key, _, value = option.partition("=")
        if key not in names:
            sys.exit(f"unknown sampling option {key!r} (steps, ensemble, reduce)")
        setattr(diffusion.config, names[key], value if key == "reduce" else int(value))
    diffusion.config.validate()
    results, offset = {}, 0
    for scene, arrays in shards:
        # seeds continue across scenes so each triple's noise matches `esgs ndn eval` on the split
        results[scene] = evaluate_arrays(model, diffusion, arrays, seed=offset)
        offset += len(arrays["views"])
    return results


def score_sfm(data_dir: Path, shards: list[tuple[str, dict]]) -> tuple[dict[str, list[dict]], dict]:
    from esgs.core.colmap import read_model
    from esgs.core.ndn.baselines import sfm_baseline_maps, triangulate_known_poses
    from esgs.core.ndn.infer import score_view

    results, coverage = {}, {}
    for scene, arrays in shards:
        scene_dir = data_dir / "scenes" / scene
        if not scene_dir.exists():
            sys.exit(f"the SfM baseline needs the rendered scene folder {scene_dir}")
        sparse = triangulate_known_poses(scene_dir)
        camera = next(iter(read_model(scene_dir, use_pycolmap=False).cameras.values()))
        height, width = arrays["depth"].shape[-2:]
        scores, points = [], []
        for index, name in enumerate(arrays["names"]):
            depth, normal, _ = sfm_baseline_maps(sparse[str(name)], (camera.width, camera.height), (width, height),
                                                 np.asarray(camera.params))
            points.append(len(sparse[str(name)].depth))
            scores.append(score_view(depth, normal, arrays["depth"][index], arrays["normal"][index],
                                     arrays["mask"][index]))
        results[scene] = scores
        coverage[scene] = points
    return results, coverage


def summarise(per_scene: dict[str, list[dict]]) -> dict:
    every = [scores for values in per_scene.values() for scores in values]
    return {"triples": len(every), **{key: float(np.mean([s[key] for s in every])) for key in METRICS},
            "per_scene": {scene: {key: float(np.mean([s[key] for s in values])) for key in METRICS}
                          for scene, values in per_scene.items()}}


def table(results: dict[str, dict], title: str) -> str:
    lines = [f"{title}", "", "| method | triples | AbsRel | delta1 | normal mean error (deg) | < 11.25 deg |",
             "|---|---|---|---|---|---|"]
    for label, summary in results.items():
        lines.append(f"| {label} | {summary['triples']} | {summary['abs_rel']:.4f} | {summary['delta1']:.4f} | "
                     f"{summary['normal_mean_deg']:.2f} | {100 * summary['normal_within_11_25']:.1f} % |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path, nargs="+", help="data folders (shards/, scenes/)")
    parser.add_argument("--split", default="heldout", help="heldout (default) or validation")
    parser.add_argument("--method", action="append", required=True,
                        help="ndn:LABEL=CHECKPOINT, regression:LABEL=CHECKPOINT or sfm (repeatable)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None, help="write every score here (merged into an existing file)")
    args = parser.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    everything = json.loads(args.json.read_text()) if args.json and args.json.exists() else {}
    for data_dir in args.data:
        shards = scene_shards(data_dir, args.split)
        key = f"{data_dir.name}:{args.split}"
        results = everything.setdefault(key, {})
        for method in args.method:
            started = time.time()
            if method == "sfm":
                per_scene, coverage = score_sfm(data_dir, shards)
                label = "sfm-interpolated"
                results[label] = {**summarise(per_scene), "points_per_view": coverage,
                                  "views_without_points": int(sum(c == 0 for v in coverage.values() for c in v))}
            else:
                kind, _, rest = method.partition(":")
                label, _, checkpoint = rest.partition("=")
                if kind not in ("ndn", "regression") or not checkpoint:
                    sys.exit(f"cannot read --method {method!r}")
                label = f"{kind} {label}"
                results[label] = {**summarise(score_network(checkpoint, shards)), "checkpoint": checkpoint}
            results[label]["seconds"] = round(time.time() - started, 1)
            print(f"{key} {label}: {json.dumps({k: results[label][k] for k in ('triples', *METRICS)})}", flush=True)
        print(table(results, f"### {key}"))
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(everything, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
