"""Quality of GPDFN's cheaper settings against the paper's, equal steps and seeds: GPDFN every
k-th step (``gpdfn_every``) and the width of its fusion layers (``gpdfn_hidden``).

Full ESGS (``full_esgs``: depth and normal priors, GPDFN K = 3) on one scene, the runs one after
another, seed first (every setting for seed 0, then seed 1, ...), each cached in
``OUT/runs/k<k>[_h<hidden>]/seed<s>`` (a finished run is not repeated; ``_h<hidden>`` only when
the width is not the default 16). After every run ``OUT/gpdfn.md`` and ``OUT/gpdfn.json`` are
rewritten: mean and standard deviation over seeds of SSIM, PSNR, LPIPS and the
Gaussian-centre-to-mesh distances, plus training seconds.

    .venv/bin/python benchmarks/ablate_gpdfn.py SCENE --out DIR [--every 1 2] [--hidden 16 8] [--seeds 0 1 2]
        [--iterations 300] [--priors sfm] [--width 160] [--threads 1]
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# idle OpenMP threads spin by default and take the cores a busy machine's other runs need
# (docs/rasterizer.md, "Spinning OpenMP workers"); set before torch loads
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from esgs.core.config import config_to_dict  # noqa: E402
from esgs.core.experiments.ablate import available_priors  # noqa: E402
from esgs.core.experiments.runs import RunTask, run_task  # noqa: E402
from esgs.core.methods import full_esgs  # noqa: E402
from esgs.core.methods.esgs.gpdfn_settings import GPDFNConfig  # noqa: E402
from esgs.core.experiments.tables import COST_COLUMNS, QUALITY_COLUMNS, aggregate, markdown_table  # noqa: E402
from esgs.core.io_utils import atomic_write_json, atomic_write_text  # noqa: E402
from esgs.core.formats.scene_dir import SceneDir  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--every", type=int, nargs="+", default=[1])
    parser.add_argument("--hidden", type=int, nargs="+", default=[16], help="widths of GPDFN's fusion layers")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--priors", default="sfm")
    parser.add_argument("--fused-k", type=int, default=3)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)

    kinds = available_priors(args.scene).get(args.priors, set())
    if not kinds:
        parser.error(f"no priors/{args.priors}/depth or normal under {args.scene}")
    mesh = SceneDir(args.scene).ground_truth_mesh
    summaries = []
    default_hidden = GPDFNConfig.gpdfn_hidden
    for seed in args.seeds:
        for every in args.every:
            for hidden in args.hidden:
                label = f"k{every}" + ("" if hidden == default_hidden else f"_h{hidden}")
                esgs = config_to_dict(full_esgs(args.priors, scene=args.scene, depth="depth" in kinds,
                                                fused_k=args.fused_k, gpdfn_every=every, gpdfn_hidden=hidden))
                config = {"iterations": args.iterations, "seed": seed, "width": args.width, "threads": args.threads,
                          "method": "esgs", "method_config": esgs}
                task = RunTask(name=f"{label}/seed{seed}", scene=args.scene, out=args.out / "runs" / label /
                               f"seed{seed}", config=config, variant=f"GPDFN every {every}, width {hidden}", seed=seed,
                               scene_name=args.scene.name, mesh=mesh if mesh.is_file() else None,
                               measure_render=False)
                summary = run_task(task)
                summaries.append(summary)
                print(f"{task.name}: SSIM {summary['ssim']:.4f} PSNR {summary['psnr']:.2f} LPIPS "
                      f"{summary['lpips']:.4f} dist {summary['distance_mean']} train {summary['train_s']:.0f} s",
                      flush=True)
                columns = QUALITY_COLUMNS + COST_COLUMNS[:1]
                rows = aggregate(summaries, [key for key, _, _ in columns])
                table = {"scene": str(args.scene), "iterations": args.iterations, "priors": args.priors,
                         "width": args.width, "command": "python " + " ".join(sys.argv),
                         "esgs": {k: v for k, v in esgs.items() if k not in ("gpdfn_every", "gpdfn_hidden")},
                         "rows": rows, "runs": summaries}
                atomic_write_json(args.out / "gpdfn.json", table)
                atomic_write_text(args.out / "gpdfn.md",
                                  f"# GPDFN settings: {args.scene.name}\n\n{args.iterations} steps, width "
                                  f"{args.width}, priors {args.priors}, K = {args.fused_k}; mean ± std over seeds\n\n"
                                  + markdown_table(rows, columns))
    return 0


if __name__ == "__main__":
    sys.exit(main())
