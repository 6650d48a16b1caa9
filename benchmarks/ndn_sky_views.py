"""NDN weights on the views that show sky: the sky head's IoU and the depth and normal scores.

A quicker companion of ``benchmarks/ndn_completion.py`` for what the sky changes: only views
whose ground-truth mask leaves at least 2 % of the pixels without surface count, each scored
with no evidence and with the scene's own triangulated SfM points (the same triangulation the
training shards hold), at the training working size (128 px). No stereo labels are needed, so a
set of scene folders is scored in a minute or two per weights file on one thread.

    .venv/bin/python benchmarks/ndn_sky_views.py --set landform_mixed=/work/runs/c25/eval/landform_mixed_* \\
        --weights control=/work/runs/c25/reg/checkpoints/step_0001250.pt --json benchmarks/results/OUT.json
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # an idle OpenMP worker must not spin beside other jobs

import argparse  # noqa: E402
import glob  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

SKY_VIEW_SHARE = 0.02  # as benchmarks/ndn_completion.py: a view with this share of no-surface pixels has sky
MODES = ("none", "sfm")
REPORTED = ("sky_iou", "abs_rel", "delta1", "normal_mean_deg")


def scene_arrays(scene: Path) -> dict:
    """The scene's triples at the working size with their SfM depth (what the network reads)."""
    from esgs.core.ndn.data import scene_triples

    triples = scene_triples(scene, 128, 4, sfm_points=True)
    return {"views": triples.views, "depth": triples.depth, "normal": triples.normal, "mask": triples.mask,
            "sfm_depth": triples.sfm_depth}


def score_weights(weights: Path, scenes: list[dict]) -> dict[str, dict]:
    """Mean scores over the views with sky, per evidence mode."""
    from esgs.core.ndn.checkpoint import load_checkpoint
    from esgs.core.ndn.infer import mean_scores, predict_triple, score_triple

    model, diffusion, config, _ = load_checkpoint(weights)
    result = {}
    for mode in MODES if config.model.evidence else ("none",):
        per_view = []
        for data in scenes:
            for index in range(len(data["views"])):
                if float((~data["mask"][index]).mean()) < SKY_VIEW_SHARE:
                    continue
                depth, normal, sky, metric = predict_triple(model, diffusion, data, index, seed=index,
                                                            evidence_mode=mode)
                per_view.append(score_triple(depth, normal, sky, metric, data, index))
        result[mode] = {"views": len(per_view), **(mean_scores(per_view) if per_view else {})}
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--set", action="append", required=True, metavar="NAME=GLOB[,GLOB]",
                        help="an evaluation set: scene folders (globs)")
    parser.add_argument("--weights", action="append", required=True, metavar="NAME=PATH", help="weights to score")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args(argv)
    from esgs.core.io_utils import atomic_write_json

    torch.set_num_threads(args.threads)
    weights = [(text.partition("=")[0], Path(text.partition("=")[2])) for text in args.weights]
    result: dict = {"what": "NDN weights on the views with sky: sky IoU, depth (after the trainer's scale/shift fit) "
                            "and normals, no evidence and SfM evidence (benchmarks/ndn_sky_views.py)",
                    "command": " ".join(["python", "benchmarks/ndn_sky_views.py", *(argv if argv is not None
                                                                                   else sys.argv[1:])]),
                    "machine": platform.node(), "weights": {name: str(path) for name, path in weights}, "sets": {}}
    for text in args.set:
        set_name, _, patterns = text.partition("=")
        scenes = sorted(Path(p) for pattern in patterns.split(",") for p in glob.glob(pattern))
        if not scenes:
            raise SystemExit(f"set {set_name}: no scene folder matches {patterns}")
        arrays = [scene_arrays(scene) for scene in scenes]
        rows = {name: score_weights(path, arrays) for name, path in weights}
        result["sets"][set_name] = {"scenes": [str(s) for s in scenes], "rows": rows}
        atomic_write_json(args.json, result)  # after every set: a long run keeps what it has
        for name, modes in rows.items():
            for mode, scores in modes.items():
                shown = ", ".join(f"{key} {scores[key]:.3f}" for key in REPORTED if key in scores)
                print(f"[{set_name}] {name}:{mode} ({scores['views']} views) {shown}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
