"""Where a training run's memory peak sits: resident memory step by step through ``esgs train``.

Runs ``esgs train`` with the given arguments in a child process that records, for every step,
the Gaussian count, the resident size after the step (``VmRSS``) and the step's own peak
(``VmHWM``, reset before the step through ``/proc/self/clear_refs``), plus the peak of the
set-up before the first step. The run's peak is the largest of these; it is reported above the
floor of a process that only imported torch (the same floor as ``bench_vs_opensplat.py``),
with the step, the Gaussian count and the bytes per Gaussian at it (``peak_step`` is the step with
the largest peak of its own; the set-up and the end of the run, final PLY and evaluation, are
recorded apart and count towards the peak). Linux only.

    python benchmarks/memory_timeline.py --json benchmarks/results/memory_timeline.json -- \\
        train SCENE --out RUN --iterations 2000 --width 480 --threads 1 --checkpoint-every 0 --no-evaluate --quiet

Memory is measured here, never asserted in tests.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

SCRIPT = Path(__file__).resolve()


def _status_mib() -> dict[str, float]:
    values = {}
    with open("/proc/self/status") as handle:
        for line in handle:
            if line.startswith(("VmRSS:", "VmHWM:")):
                values[line.split(":")[0]] = int(line.split()[1]) / 1024.0
    return values


def _reset_peak() -> None:
    with open("/proc/self/clear_refs", "w") as handle:
        handle.write("5")  # resets VmHWM to the current resident size


def child(record: Path, cli_args: list[str]) -> int:
    """Run ``esgs`` with ``cli_args`` in this process, one JSON line per step into ``record``."""
    from esgs.core.cli import main as esgs_main
    from esgs.core.train import trainer as trainer_module

    original = trainer_module.Trainer.train_step
    out = open(record, "w")
    first = [True]

    def train_step(self: Any, step: int, *args: Any, **kwargs: Any) -> Any:
        if first[0]:  # everything before the first step: imports, scene, initial Gaussians
            first[0] = False
            out.write(json.dumps({"setup_peak_mib": _status_mib()["VmHWM"], "gaussians": len(self.gaussians)}) + "\n")
        _reset_peak()
        before = len(self.gaussians)
        result = original(self, step, *args, **kwargs)
        status = _status_mib()
        out.write(json.dumps({"step": step, "gaussians_before": before, "gaussians": len(self.gaussians),
                              "rss_mib": status["VmRSS"], "peak_mib": status["VmHWM"]}) + "\n")
        out.flush()
        return result

    trainer_module.Trainer.train_step = train_step
    try:
        code = int(esgs_main(cli_args) or 0)
        # since the last step's reset: the end of the run (final PLY, evaluation)
        out.write(json.dumps({"end_peak_mib": _status_mib()["VmHWM"]}) + "\n")
        return code
    finally:
        out.close()


def summarise(lines: list[dict], floor_mib: float, every: int = 10) -> dict[str, Any]:
    """The run's peak and where it sits, from :func:`child`'s records."""
    setup = next((line for line in lines if "setup_peak_mib" in line), None)
    steps = [line for line in lines if "step" in line]
    if setup is None or not steps:
        raise SystemExit("the run recorded no training step")
    top = max(steps, key=lambda line: line["peak_mib"])
    end = next((line["end_peak_mib"] for line in lines if "end_peak_mib" in line), float("nan"))
    peak = max(top["peak_mib"], setup["setup_peak_mib"], end if end == end else 0.0)
    at_most = max(line["gaussians"] for line in steps)
    densifying = [line for line in steps if line["gaussians"] != line["gaussians_before"]]
    return {
        "floor_mib": floor_mib, "peak_mib": peak, "peak_above_floor_mib": peak - floor_mib,
        "setup_peak_mib": setup["setup_peak_mib"], "end_peak_mib": end, "peak_step": top["step"],
        "gaussians_at_peak_step": top["gaussians"], "max_gaussians": at_most,
        "bytes_above_floor_per_gaussian_at_max": (peak - floor_mib) * 2**20 / max(at_most, 1),
        "steps": len(steps), "densifying_steps": len(densifying),
        # every K-th step and the peak's: resident size after the step and the step's own peak
        "timeline": [{key: line[key] for key in ("step", "gaussians", "rss_mib", "peak_mib")}
                     for line in steps if line["step"] % every == 0 or line is top],
    }


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--child"]:
        return child(Path(argv[1]), argv[2:])
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     usage="%(prog)s [--json OUT] [--every K] -- ESGS_ARGS...")
    parser.add_argument("--json", type=Path, default=None, help="write the figures and the timeline here")
    parser.add_argument("--every", type=int, default=10, help="keep every K-th step in the JSON timeline")
    if "--" not in argv:
        parser.error("give the esgs arguments after --, e.g. -- train SCENE --out RUN --iterations 500")
    split = argv.index("--")
    args, cli_args = parser.parse_args(argv[:split]), argv[split + 1:]
    if not sys.platform.startswith("linux"):
        print("SKIP: reading peaks from /proc needs Linux")
        return 0
    sys.path.insert(0, str(SCRIPT.parent))
    from bench_vs_opensplat import floor_rss_mib

    floor = floor_rss_mib([sys.executable, "-c", "import torch"], dict(os.environ))
    with tempfile.TemporaryDirectory(prefix="esgs_memory_") as work:
        record = Path(work) / "steps.jsonl"
        done = subprocess.run([sys.executable, str(SCRIPT), "--child", str(record), *cli_args])
        if done.returncode != 0:
            raise SystemExit(f"esgs {' '.join(cli_args)} failed (exit {done.returncode})")
        lines = [json.loads(line) for line in record.read_text().splitlines() if line.strip()]
    result = {"command": " ".join(["python", "benchmarks/memory_timeline.py", *argv]), **summarise(lines, floor, args.every)}
    print(f"floor (python + import torch) {floor:.0f} MiB; peak {result['peak_mib']:.0f} MiB at step "
          f"{result['peak_step']} ({result['gaussians_at_peak_step']:,} Gaussians), "
          f"{result['peak_above_floor_mib']:.0f} MiB above the floor; set-up peak {result['setup_peak_mib']:.0f} MiB; "
          f"{result['bytes_above_floor_per_gaussian_at_max']:.0f} bytes above the floor per Gaussian at the most "
          f"({result['max_gaussians']:,})")
    if args.json is not None:
        from esgs.core.io_utils import atomic_write_json

        args.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
