"""Time and disk size of Preferences > Set Up Trainer: the real plan, run into a temporary folder.

Runs :func:`esgs.esgs_addon.trainer_setup.run_setup` (venv, torch, the pinned trainer set, the
engine, the verify step with a test render) and records each step's seconds, the finished
environment's size on disk and, per package, the size of the wheel pip installed (what a user
downloads). The package sources are the caller's: pass ``--index-url`` / ``--find-links`` to
point at a local wheel folder or a mirror; the time then leaves the download out, which the
wheel sizes let a reader add for their own connection.

    python benchmarks/bench_trainer_setup.py --python python3.11 --variant cpu \\
        --index-url https://pypi.org/simple --find-links /opt/wheels \\
        --json benchmarks/results/trainer_setup.json

Nothing is kept: the environment is removed at the end (``--keep DIR`` builds it there and keeps it).
"""
from __future__ import annotations

import argparse
import os
import platform
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def folder_size(path: Path) -> int:
    """Bytes of the files under ``path`` (links not followed, each file once)."""
    total, seen = 0, set()
    for root, _dirs, files in os.walk(path):
        for name in files:
            stat = os.lstat(os.path.join(root, name))
            if (stat.st_dev, stat.st_ino) not in seen:
                seen.add((stat.st_dev, stat.st_ino))
                total += stat.st_blocks * 512
    return total


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--python", default=sys.executable, help="the Python 3.11 that creates the environment")
    parser.add_argument("--variant", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--index-url", default=None)
    parser.add_argument("--find-links", nargs="*", default=None)
    parser.add_argument("--keep", type=Path, default=None, help="build here and keep it")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)

    from esgs.esgs_addon.trainer_setup import run_setup

    work = Path(tempfile.mkdtemp(prefix="esgs_trainer_bench_")) if args.keep is None else args.keep.parent
    target = (work / "trainer") if args.keep is None else args.keep
    steps: list[dict[str, Any]] = []
    wheels: dict[str, int] = {}
    started = time.perf_counter()
    step_started = [started]

    def on_line(line: str) -> None:
        now = time.perf_counter()
        if line.startswith("==> "):
            if steps:
                steps[-1]["seconds"] = now - step_started[0]
            steps.append({"step": line[4:].strip()})
            step_started[0] = now
        # pip: "Downloading name-1.2-....whl (12.3 MB)" / "Processing /path/name-1.2-....whl"
        downloaded = re.search(r"Downloading \S*?([^/\s]+\.whl) \(([\d.]+) (kB|MB|GB)\)", line)
        local = re.search(r"Processing (\S+\.whl)\s*$", line)
        if downloaded:
            factor = {"kB": 1e3, "MB": 1e6, "GB": 1e9}[downloaded.group(3)]
            wheels.setdefault(downloaded.group(1), int(float(downloaded.group(2)) * factor))
        elif local and Path(local.group(1)).is_file():
            wheels.setdefault(Path(local.group(1)).name, Path(local.group(1)).stat().st_size)
        print(line, flush=True)

    try:
        found = run_setup(target, python=args.python, variant=args.variant, find_links=args.find_links,
                          index_url=args.index_url, on_line=on_line)
        total = time.perf_counter() - started
        if steps and "seconds" not in steps[-1]:
            steps[-1]["seconds"] = time.perf_counter() - step_started[0]
        size = folder_size(target)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    result = {"command": "python " + " ".join([sys.argv[0], *(argv if argv is not None else sys.argv[1:])]),
              "machine": f"{platform.system()} {platform.machine()}, {os.cpu_count()} cores",
              "variant": args.variant, "index_url": args.index_url, "find_links": args.find_links,
              "total_s": total, "steps": steps, "environment_bytes": size,
              "environment_gib": size / 2**30, "wheel_bytes": wheels,
              "wheel_bytes_total": sum(wheels.values()), "check": found}
    print(f"set-up {total:.0f} s, environment {size / 2**30:.2f} GiB, wheels {sum(wheels.values()) / 2**20:.0f} MiB")
    for step in steps:
        print(f"  {step.get('seconds', float('nan')):7.1f} s  {step['step']}")
    if args.json:
        from esgs.core.io_utils import atomic_write_json

        atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
