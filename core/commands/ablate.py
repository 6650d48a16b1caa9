"""``esgs ablate SCENE --out DIR``: the paper's ablation grid, prior-source and fused-K studies."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "run the ablation studies (3DGS, +depth, +normal, +both, +all; prior sources; GPDFN K) on one scene"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", type=Path, help="scene folder (images/, sparse/0, priors/, mesh/ground_truth.ply)")
    parser.add_argument("--out", type=Path, required=True, help="experiment folder (runs/ and ablation.md/.json)")
    parser.add_argument("--iterations", type=int, default=3000, help="training steps of every run (default: 3000)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="seeds (default: 0)")
    parser.add_argument("--priors", default="",
                        help="prior source of the grid and K studies (default: first of gt, labels, ndn, sfm)")
    parser.add_argument("--studies", default="grid,priors,fused_k",
                        help="comma-separated studies to run: grid, priors, fused_k (default: all three)")
    parser.add_argument("--fused-k", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="K values of the GPDFN study")
    parser.add_argument("--width", type=int, default=0, help="train at this image width (0 = full size)")
    parser.add_argument("--threads", type=int, default=0, help="CPU threads per run (0 = library default)")
    parser.add_argument("--backend", default="auto", help="rasterizer backend (auto, cpu, reference, cuda)")
    parser.add_argument("--lpips", action=argparse.BooleanOptionalAction, default=True, help="compute LPIPS")


def run(args: argparse.Namespace) -> int:
    from ..experiments.ablate import run_ablation

    def report(task, status: str) -> None:
        print(f"{status:>8}  {task.name}", flush=True)

    train = {"width": args.width, "threads": args.threads, "backend": args.backend, "lpips": args.lpips}
    table = run_ablation(args.scene, args.out, iterations=args.iterations, seeds=args.seeds, priors=args.priors,
                         fused_ks=args.fused_k, train=train, on_run=report,
                         studies=[name.strip() for name in args.studies.split(",") if name.strip()])
    print(f"wrote {Path(args.out) / 'ablation.md'}")
    for item in table["failed"]:
        print(f"FAILED {item['run']}: {item['error']}")
    return 1 if table["failed"] else 0
