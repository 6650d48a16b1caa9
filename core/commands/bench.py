"""``esgs bench --suite quick|full --out DIR``: 3DGS, Mip-Splatting, DropoutGS and ESGS compared."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "compare 3DGS, Mip-Splatting, DropoutGS, ESGS ablations and ESGS on synthetic scenes (benchmarks.md)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--suite", choices=("quick", "full"), default="quick",
                        help="quick: cratered_plain seed 0, 10 views 160x90, 300 points/view, 300 steps (~8 min on 2 busy cores); "
                             "full: cratered_plain, dune_field, rocky_slope, crater_survey_nadir x seeds 0 1 2, "
                             "30 views 480x270, 7000 steps")
    parser.add_argument("--out", type=Path, required=True, help="bench folder (scenes/, runs/, benchmarks.md)")
    parser.add_argument("--iterations", type=int, default=0, help="steps per run (0 = the suite's)")
    parser.add_argument("--workers", type=int, default=1, help="runs at the same time (local process pool)")
    parser.add_argument("--address", default=None,
                        help="Ray cluster address ('auto' = local Ray): run through Ray (needs the ray package)")
    parser.add_argument("--executor", choices=("auto", "local", "ray"), default="auto",
                        help="auto: Ray when --address is given, else the local process pool")
    parser.add_argument("--threads", type=int, default=0, help="CPU threads per run (0 = library default)")
    parser.add_argument("--backend", default="auto", help="rasterizer backend (auto, cpu, reference, cuda)")
    parser.add_argument("--lpips", action=argparse.BooleanOptionalAction, default=True, help="compute LPIPS")


def run(args: argparse.Namespace) -> int:
    from ..experiments.bench import run_bench
    from ..experiments.executor import make_executor

    def report(outcome) -> None:
        print(f"{outcome.status:>8}  {outcome.task.name}", flush=True)

    train = {"threads": args.threads, "backend": args.backend, "lpips": args.lpips}
    with make_executor(args.executor, max_workers=args.workers, address=args.address) as executor:
        result = run_bench(args.out, args.suite, executor=executor, iterations=args.iterations or None, train=train,
                           command="esgs " + " ".join(sys.argv[1:]), on_outcome=report)
    print(f"wrote {Path(args.out) / 'benchmarks.md'}")
    for item in result["failed"]:
        print(f"FAILED {item['run']}: {item['error'].splitlines()[0]}")
    return 1 if result["failed"] else 0
