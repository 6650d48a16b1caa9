"""Label accuracy on synthetic scenes: AbsRel / delta1 of ``esgs labels --reconstruct``
against the ground-truth depth (the paper's annotation pipeline: AbsRel 0.065, delta1 0.973).

For each preset: generate the scene with ``esgs scene`` (reused when ``--work`` already holds
it), run ``esgs labels SCENE --reconstruct --report`` (mesh rebuilt from the scene's own
images and poses; never the exact mesh), and collect the accuracy report. Prints a table and
writes all figures to ``--out`` (JSON), with timings and the machine's load average.

    .venv/bin/python benchmarks/bench_labels.py --work /tmp/labels_bench \\
        [--presets cratered_plain rocky_slope] [--seed 3] [--views 12] [--resolution 320x180] [--samples 8]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from esgs.core.formats.scene_dir import SceneDir


def _esgs(*arguments: str) -> None:
    subprocess.run([sys.executable, "-m", "esgs.core", *arguments], check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True, help="folder for the scenes (reused when present)")
    parser.add_argument("--presets", nargs="+", default=["cratered_plain", "rocky_slope"])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--resolution", default="320x180")
    parser.add_argument("--samples", type=int, default=8)
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON file for the results (default: WORK/labels_accuracy.json)")
    args = parser.parse_args()

    results = {"settings": {"seed": args.seed, "views": args.views, "resolution": args.resolution,
                            "samples": args.samples}, "scenes": {}}
    for preset in args.presets:
        scene = args.work / f"{preset}_s{args.seed}_v{args.views}_{args.resolution}"
        folder = SceneDir(scene)
        start = time.perf_counter()
        if not folder.provenance.is_file():
            _esgs("scene", "--preset", preset, "--seed", str(args.seed), "--views", str(args.views),
                  "--resolution", args.resolution, "--samples", str(args.samples), "--out", str(scene))
        scene_seconds = time.perf_counter() - start
        start = time.perf_counter()
        _esgs("labels", str(scene), "--reconstruct", "--report")
        label_seconds = time.perf_counter() - start
        accuracy = json.loads(folder.labels_accuracy.read_text())
        reconstruction = json.loads(folder.reconstruction_report.read_text())
        accuracy.pop("views", None)
        results["scenes"][preset] = {"accuracy": accuracy, "reconstruction": {
            key: reconstruction[key] for key in ("fused_points", "triangles", "cell_size", "stereo_fraction",
                                                 "consistent_fraction", "seconds")},
            "scene_seconds": round(scene_seconds, 1), "labels_seconds": round(label_seconds, 1)}
    results["load_average"] = os.getloadavg()
    out = args.out or args.work / "labels_accuracy.json"
    out.write_text(json.dumps(results, indent=2))
    print(f"\n{'preset':<16}{'AbsRel':>9}{'delta1':>9}{'coverage':>10}{'filled AbsRel':>15}"
          f"{'baseline AbsRel':>17}{'labels s':>10}")
    for preset, result in results["scenes"].items():
        accuracy = result["accuracy"]
        print(f"{preset:<16}{accuracy['overall']['abs_rel']:>9.4f}{accuracy['overall']['delta1']:>9.4f}"
              f"{100 * accuracy['coverage']:>9.1f}%{accuracy['filled']['abs_rel']:>15.4f}"
              f"{accuracy['baseline_median_depth']['abs_rel']:>17.4f}{result['labels_seconds']:>10.1f}")
    print(f"paper (annotation pipeline): AbsRel 0.065, delta1 0.973; load average {results['load_average'][0]:.1f}; "
          f"results in {out}")


if __name__ == "__main__":
    main()
