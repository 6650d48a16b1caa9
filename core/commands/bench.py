"""``esgs bench --suite quick|full|large --out DIR``: 3DGS, Mip-Splatting, DropoutGS, PGSR, Scaffold-GS,
3DGS + GPDFN and ESGS compared."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = ("compare 3DGS, Mip-Splatting, DropoutGS, PGSR, Scaffold-GS, 3DGS + GPDFN, ESGS ablations and ESGS on "
        "synthetic scenes (benchmarks.md)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--suite", choices=("quick", "full", "large"), default="quick",
                        help="quick: cratered_plain seed 0, 10 views 160x90, 300 steps + 0.5 min budgets (15-30 min "
                             "on 2 busy cores); full: cratered_plain, dune_field x seeds 0 1 2, 12 views 320x180, 500 steps "
                             "+ 1 min budgets (~1.5 h on 2 idle cores, through Ray); large: 4 presets x 3 seeds, 30 views "
                             "480x270, 7000 steps + 20 min budgets (for a GPU machine or a Ray cluster)")
    parser.add_argument("--out", type=Path, required=True,
                        help="bench folder (scenes/, runs/, runs_budget*/, benchmarks.md)")
    parser.add_argument("--iterations", type=int, default=0, help="steps per equal-step run (0 = the suite's)")
    parser.add_argument("--budget-minutes", type=float, nargs="+", default=None, metavar="M",
                        help="training minutes per equal-budget run; several (e.g. 1 5) give one equal-budget "
                             "comparison each (default: the suite's; 0 alone = no budget comparison)")
    parser.add_argument("--budget-step-cap", type=int, default=0,
                        help="step cap (and schedule length) of the shortest budget's runs, scaled by the minutes "
                             "for the longer ones (0 = the suite's: twice --iterations)")
    parser.add_argument("--rows", nargs="+", default=None, metavar="KEY",
                        help="train only these rows (default: all): 3dgs, 3dgs_sky, mip_splatting, dropout_gs, pgsr, "
                             "scaffold_gs, 3dgs_gpdfn, esgs_depth, esgs_normal, esgs_depth_normal, esgs_full (one row "
                             "per --priors source), esgs_full_gt (the upper bound)")
    parser.add_argument("--eval-every", type=int, default=None, metavar="K",
                        help="evaluate the held-out views of every equal-step run every K steps, the curves of the "
                             "report's 'time to 3DGS's quality' table (default: a tenth of --iterations; 0 = only at "
                             "the end of each run)")
    parser.add_argument("--priors", nargs="+", choices=("auto", "labels", "ndn", "sfm", "gt"), default=["auto"],
                        metavar="SOURCE",
                        help="prior source(s) of the ESGS rows: auto (default: stereo labels, NDN and SfM fused per "
                             "pixel with a confidence, as esgs train --esgs uses), labels (esgs labels --reconstruct, "
                             "needs bpy), ndn, sfm, or gt (the generator's exact maps, flattering); made per scene when "
                             "missing. Several (e.g. --priors auto labels ndn) give one full-ESGS row 'ESGS (SOURCE)' "
                             "each, side by side; the ablation rows use the first. A labelled upper-bound row with gt "
                             "priors is always added")
    parser.add_argument("--sparse-points", choices=("triangulated", "exact"), default="triangulated",
                        help="the scenes' SfM points (initial Gaussians, sfm priors, NDN pinning): triangulated "
                             "(default) = SIFT matches of the rendered images with the known poses, as a real capture "
                             "gives; exact = the generator's surface samples (flatter every method's geometry; the "
                             "bench's tables before the triangulated scenes)")
    parser.add_argument("--executor", choices=("auto", "local", "ray"), default="auto",
                        help="local: process pool of --workers; ray: a local Ray instance (nothing to set up) or the "
                             "cluster at --address; auto: Ray for --address or the full/large suites, else local")
    parser.add_argument("--address", default=None,
                        help="address of an existing Ray cluster (e.g. 'auto' or 'HOST:6379'); implies --executor ray")
    parser.add_argument("--workers", type=int, default=0,
                        help="runs at the same time (0 = 1 for the local pool, all cores for a local Ray instance)")
    parser.add_argument("--threads", type=int, default=0,
                        help="CPU threads per run (0 = library default; under Ray each run reserves "
                             "max(1, threads) CPUs)")
    parser.add_argument("--backend", default="auto", help="rasterizer backend (auto, cpu, reference, cuda)")
    parser.add_argument("--lpips", action=argparse.BooleanOptionalAction, default=True, help="compute LPIPS")


def executor_kind(args: argparse.Namespace) -> str:
    """The executor the arguments ask for: "auto" resolves to Ray for --address and the big suites."""
    if args.executor != "auto":
        return args.executor
    return "ray" if args.address or args.suite in ("full", "large") else "local"


def run(args: argparse.Namespace) -> int:
    from ..errors import ConfigError
    from ..experiments.bench import run_bench, select_methods
    from ..experiments.executor import make_executor

    def report(outcome) -> None:
        print(f"{outcome.status:>8}  {outcome.task.name}", flush=True)

    kind = executor_kind(args)
    if args.address and kind != "ray":
        raise ConfigError("--address needs the Ray executor", hint="drop --executor local, or drop --address")
    methods = select_methods(args.rows)
    train = {"threads": args.threads, "backend": args.backend, "lpips": args.lpips}
    with make_executor(kind, max_workers=args.workers, address=args.address,
                       cpus_per_task=max(1, args.threads)) as executor:
        result = run_bench(args.out, args.suite, executor=executor, iterations=args.iterations or None,
                           budget_minutes=args.budget_minutes, budget_step_cap=args.budget_step_cap or None,
                           methods=methods, train=train, priors=args.priors, sparse_points=args.sparse_points,
                           eval_every=args.eval_every,
                           command="esgs " + " ".join(sys.argv[1:]), on_outcome=report)
    print(f"wrote {Path(args.out) / 'benchmarks.md'}")
    for item in result["failed"]:
        print(f"FAILED {item['run']}: {item['error'].splitlines()[0]}")
    return 1 if result["failed"] else 0
