"""Label accuracy of the same scenes labelled several ways, side by side (synthetic scenes with ``priors/gt``).

Each arm is a folder of scene copies that differ only in their ``priors/labels`` (made with
other ``esgs labels --reconstruct`` options); every copy is scored by
:func:`esgs.core.labels.accuracy.label_accuracy` (AbsRel, delta1 and coverage over every
labelled surface pixel) and the arms are pooled per set of scenes (pixel-weighted), also by
true depth in fixed bins, so that a change to stereo or meshing is judged where it acts.

    .venv/bin/python benchmarks/labels_arms.py --arm before=/work/runs/rv/work --arm after=/work/runs/rv/work_new \\
        --set rover='rover_*_sfm' --set landform='landform_*_sfm' --json benchmarks/results/labels_arms_DATE.json
"""
from __future__ import annotations

import argparse
import glob
import sys
from pathlib import Path

import numpy as np

#: True-depth bins (scene units; metres on the synthetic and real-mesh scenes).
BINS = (0.0, 5.0, 10.0, 20.0, 40.0, 80.0, float("inf"))


def pooled_scores(copies: list[Path]) -> dict:
    """Pixel-pooled AbsRel / delta1 / coverage of the copies' labels, overall and by true depth."""
    from esgs.core.formats.scene_dir import PriorSource, SceneDir
    from esgs.core.priors.io import load_prior_maps

    ratios, errors, depths, surface_pixels = [], [], [], 0
    for copy in copies:
        for image in sorted(SceneDir(copy).images.iterdir()):
            truth = load_prior_maps(copy, PriorSource.GT, image.name)
            labels = load_prior_maps(copy, PriorSource.LABELS, image.name)
            surface = truth.mask & (truth.depth > 0)
            both = surface & labels.mask & (labels.depth > 0)
            surface_pixels += int(surface.sum())
            label, true = labels.depth[both].astype(np.float64), truth.depth[both].astype(np.float64)
            ratios.append(np.maximum(label / true, true / label))
            errors.append(np.abs(label - true) / true)
            depths.append(true)
    ratio, error, depth = (np.concatenate(values) for values in (ratios, errors, depths))

    def scores(select: np.ndarray) -> dict:
        count = int(select.sum())
        return {"pixels": count, "abs_rel": float(error[select].mean()) if count else None,
                "delta1": float((ratio[select] < 1.25).mean()) if count else None}

    return {"scenes": [str(c) for c in copies], "coverage": len(depth) / max(surface_pixels, 1),
            **scores(np.ones(len(depth), bool)),
            "by_depth": [{"min": low, "max": high, **scores((depth >= low) & (depth < high))}
                         for low, high in zip(BINS[:-1], BINS[1:])]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arm", action="append", required=True, metavar="NAME=FOLDER")
    parser.add_argument("--set", action="append", required=True, metavar="NAME=GLOB",
                        help="scene copies inside each arm's folder")
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args(argv)
    result: dict = {"what": "label accuracy per arm (benchmarks/labels_arms.py)",
                    "command": " ".join([Path(sys.executable).name, *sys.argv]), "sets": {}}
    for text in args.set:
        set_name, _, pattern = text.partition("=")
        result["sets"][set_name] = {}
        for arm_text in args.arm:
            arm, _, folder = arm_text.partition("=")
            copies = sorted(Path(p) for p in glob.glob(str(Path(folder) / pattern)))
            if not copies:
                continue
            scores = pooled_scores(copies)
            result["sets"][set_name][arm] = scores
            bins = " ".join(f"{b['delta1']:.3f}" if b["delta1"] is not None else "-" for b in scores["by_depth"])
            print(f"{set_name:10s} {arm:14s} AbsRel {scores['abs_rel']:.4f} d1 {scores['delta1']:.3f} "
                  f"coverage {scores['coverage']:.3f} | d1 by depth {bins}", flush=True)
    from esgs.core.io_utils import atomic_write_json

    atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
