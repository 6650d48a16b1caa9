"""A device_study.py plan of what a user gets by default: plain ``esgs train`` (3DGS with the
sky model) against ``esgs train --esgs`` (full ESGS on ``auto`` priors, as
:func:`esgs.core.methods.full_esgs` defines it), every scene x seed, equal steps.

    .venv/bin/python benchmarks/defaults_plan.py SCENE [SCENE ...] --out PLAN.json \
        [--seeds 0 1 2] [--iterations 600] [--threads 1] [--backend cpu]
    .venv/bin/python benchmarks/device_study.py run PLAN.json --out DIR --workers 2 --deadline-s 100000
    .venv/bin/python benchmarks/device_study.py merge DIR --json RESULT.json

Groups are the scene folders' names; arms ``3dgs_default`` and ``esgs_default`` (the names the
outdoor reports of docs/esgs_acceptance.md use), so ``merge`` gives the held-out PSNR / SSIM /
LPIPS, the sky and ground views' PSNR and the opaque centres' mean and median distance to each
scene's true mesh, mean and spread over the seeds. The scenes need their ``auto`` priors
(``esgs priors SCENE --method auto``): the plan records the settings ``full_esgs`` picks for
each scene's priors.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from esgs.core.config import config_to_dict
from esgs.core.methods import full_esgs


def plan_entries(scenes: list[Path], *, seeds: list[int], iterations: int, threads: int,
                 backend: str) -> list[dict]:
    """Seed-major entries (every scene's first seed first), 3DGS before ESGS."""
    # full ESGS's settings depend on the scene's priors only: once per scene, not per seed
    esgs_of = {scene: config_to_dict(full_esgs("auto", scene=scene)) for scene in scenes}
    entries = []
    for seed in seeds:
        for scene in scenes:
            train = {"iterations": iterations, "threads": threads, "backend": backend, "seed": seed}
            esgs = esgs_of[scene]
            for arm, config in (("3dgs_default", train),
                                ("esgs_default", {**train, "method": "esgs", "method_config": esgs})):
                entries.append({"name": f"{scene.name}/{arm}/seed{seed}", "group": scene.name, "arm": arm,
                                "seed": seed, "scene": str(scene), "config": config})
    return entries


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", type=Path, nargs="+")
    parser.add_argument("--out", type=Path, required=True, help="the plan's JSON file")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--backend", default="cpu")
    args = parser.parse_args(argv)
    entries = plan_entries([scene.resolve() for scene in args.scenes], seeds=args.seeds,
                           iterations=args.iterations, threads=args.threads, backend=args.backend)
    args.out.write_text(json.dumps(entries, indent=1))
    print(f"{len(entries)} runs -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
