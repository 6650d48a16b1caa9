"""glibc malloc settings against step time and peak memory, side by side in one run.

On this machine a first touch of a 4 KiB page costs several microseconds, so a step that
allocates fresh large tensors (every gradient of the model, the backward's buffers) pays for
faulting them in each time glibc has given the memory back to the system: blocks above its mmap
threshold (at most 32 MiB) are unmapped on free, and the heap's top is trimmed above its trim
threshold. Each variant below sets glibc's tunables through the environment (``MALLOC_*_``, read
by glibc when the process starts; ``THP_MEM_ALLOC_ENABLE`` makes torch ask for transparent huge
pages on blocks of 2 MiB and more, read when torch starts; nothing else changes) and runs, as child
processes:

- ``profile_step.py`` (seconds per step of the 3DGS and full-ESGS arms at a Gaussian count and
  width), and
- ``scale_curve.py`` (seconds per step and peak RSS of 3DGS at larger counts),

collecting their JSON outputs into one file. Variants take turns round by round.

    python benchmarks/bench_allocator.py /work/runs/mixed_s4_480 --rounds 1 \\
        --json benchmarks/results/allocator_2026-11-30.json

Speed is measured here, never asserted in tests. Run it on an otherwise idle machine.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
MIB = 2**20

#: name -> glibc tunables (environment variables read by malloc at start-up).
VARIANTS: dict[str, dict[str, str]] = {
    "glibc default": {},
    "reuse below 32 MiB": {"MALLOC_MMAP_THRESHOLD_": str(32 * MIB), "MALLOC_TRIM_THRESHOLD_": str(512 * MIB)},
    "heap only": {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": str(1024 * MIB), "MALLOC_TOP_PAD_": str(64 * MIB)},
    "heap only + THP": {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": str(1024 * MIB),
                        "MALLOC_TOP_PAD_": str(64 * MIB), "THP_MEM_ALLOC_ENABLE": "1"},
}


def _child(script: str, arguments: list[str], environment: dict[str, str]) -> dict:
    """Run ``benchmarks/<script>`` with ``arguments`` plus ``--json`` under ``environment``."""
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "out.json"
        command = [sys.executable, str(HERE / script), *arguments, "--json", str(out)]
        # the variant's settings only: none inherited from this process's environment
        inherited = {name: value for name, value in os.environ.items()
                     if not name.startswith("MALLOC_") and name not in ("GLIBC_TUNABLES", "THP_MEM_ALLOC_ENABLE")}
        env = {**inherited, "OMP_WAIT_POLICY": "PASSIVE", **environment}
        print("  ", " ".join(f"{k}={v}" for k, v in environment.items()), " ".join(command[1:]), flush=True)
        subprocess.run(command, check=True, env=env, stdout=subprocess.DEVNULL)
        return json.loads(out.read_text(encoding="utf-8"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--step-gaussians", type=int, nargs="+", default=[300000, 100000])
    parser.add_argument("--step-widths", type=int, nargs="+", default=[240, 480],
                        help="width of each --step-gaussians entry")
    parser.add_argument("--curve-gaussians", type=int, nargs="+", default=[1000000])
    parser.add_argument("--curve-width", type=int, default=480)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if len(args.step_widths) != len(args.step_gaussians):
        parser.error("give one --step-widths entry per --step-gaussians entry")

    report: dict = {"command": " ".join(["python", "benchmarks/bench_allocator.py", *(argv or sys.argv[1:])]),
                    "scene": args.scene, "threads": args.threads, "variants": {n: VARIANTS[n] for n in args.variants},
                    "load_average_start": list(os.getloadavg()), "rounds": []}
    for round_number in range(args.rounds):
        results: dict = {}
        for name in args.variants:
            print(f"round {round_number + 1}, {name}", flush=True)
            environment = VARIANTS[name]
            entry: dict = {"steps": [], "curve": None}
            for gaussians, width in zip(args.step_gaussians, args.step_widths):
                profile = _child("profile_step.py", [args.scene, "--gaussians", str(gaussians), "--width", str(width),
                                                     "--threads", str(args.threads), "--steps", "10", "--repeats", "2",
                                                     "--arms", "3dgs", "full esgs"], environment)
                entry["steps"].append({"gaussians": gaussians, "width": width,
                                       "mean_s": {arm: value["mean_s"] for arm, value in profile["arms"].items()}})
            curve = _child("scale_curve.py", [args.scene, "--widths", str(args.curve_width), "--threads",
                                              str(args.threads), "--steps", "6", "--warmup", "2", "--gaussians",
                                              *map(str, args.curve_gaussians)], environment)
            entry["curve"] = [{key: point[key] for key in ("gaussians", "width", "mean_s", "peak_rss_mib",
                                                           "above_floor_mib")} for point in curve["points"]]
            entry["curve_floor_mib"] = curve["floor"]["peak_rss_mib"]
            results[name] = entry
        report["rounds"].append(results)
    report["load_average_end"] = list(os.getloadavg())

    print("\nseconds per step (mean of the rounds); peak RSS of scale_curve")
    for name in args.variants:
        cells = []
        for index, (gaussians, width) in enumerate(zip(args.step_gaussians, args.step_widths)):
            for arm in ("3dgs", "full esgs"):
                values = [r[name]["steps"][index]["mean_s"][arm] for r in report["rounds"]]
                cells.append(f"{arm} {gaussians // 1000}k/{width} {1e3 * sum(values) / len(values):6.1f} ms")
        for index, gaussians in enumerate(args.curve_gaussians):
            points = [r[name]["curve"][index] for r in report["rounds"]]
            cells.append(f"3dgs {gaussians // 1000}k/{args.curve_width} "
                         f"{1e3 * sum(p['mean_s'] for p in points) / len(points):6.1f} ms, "
                         f"peak {max(p['peak_rss_mib'] for p in points):6.0f} MiB")
        print(f"{name:22s} " + " | ".join(cells))
    if args.json is not None:
        from esgs.core.io_utils import atomic_write_json

        atomic_write_json(args.json, report)
        print("wrote", args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
