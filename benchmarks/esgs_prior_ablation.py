"""Which part of ESGS moves the opaque Gaussians relative to the true mesh: a plan for device_study.

Writes a :mod:`device_study` plan that trains, on one scene with exact (``gt``) priors, plain
3DGS (the defaults) and ESGS with one part at a time: the full method, without GPDFN, the
depth prior alone (at several weights, in log and inverse-depth mode, with the densification
statistic fed by the images only), the normal prior alone, and GPDFN alone. Exact priors
isolate the method from the quality of the priors: if a part moves the Gaussians away from
the mesh with exact depth and normals, no better prior will fix it.

    python benchmarks/esgs_prior_ablation.py SCENE PLAN.json [--seeds 0] [--arms A ...] [--backend cpu] [--threads 2]
    python benchmarks/device_study.py run PLAN.json --out DIR --workers 1 --deadline-s 3000
    python benchmarks/device_study.py merge DIR --json RESULT.json
    python benchmarks/esgs_prior_ablation.py signed RESULT.json DIR ... --mesh SCENE/mesh/ground_truth.ply

``signed`` adds, per run, on which side of the mesh the opaque centres lie (the share above
it along the closest face's normal, the median and the 10th / 90th percentiles of the signed
distance; 4,000 centres drawn with seed 0): a prior that makes the rendered depth exact can
still leave the opaque Gaussians on one side of the surface.

(``SCENE`` is written into the plan as given: an absolute path here, where the mesh is.)
"""
from __future__ import annotations

import argparse
import json
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any


def ablation_arms() -> dict[str, dict[str, Any]]:
    """TrainConfig overrides per arm (the ESGS ones on ``gt`` priors)."""
    from esgs.core.methods import full_esgs
    from esgs.core.methods.esgs.config import ESGSConfig

    full = full_esgs("gt")
    depth = replace(full, gpdfn=False, normal=False)

    def esgs(settings: ESGSConfig, **extra: Any) -> dict[str, Any]:
        return {"method": "esgs", "method_config": asdict(settings), **extra}

    return {
        "default": {},
        "esgs_gt": esgs(full),
        "esgs_gt_nogpdfn": esgs(replace(full, gpdfn=False)),
        "esgs_gt_depth": esgs(depth),
        "depth_w0.1": esgs(replace(depth, depth_weight=0.1)),
        "depth_w1e-6": esgs(replace(depth, depth_weight=1e-6)),
        "depth_photometric": esgs(depth, densify_gradient="photometric"),
        "depth_inverse": esgs(replace(depth, depth_mode="inverse")),
        "esgs_gt_inverse": esgs(replace(full, depth_mode="inverse")),
        "esgs_gt_normal": esgs(replace(full, gpdfn=False, depth=False)),
        "gpdfn_only": esgs(ESGSConfig(gpdfn=True, fused_k=full.fused_k)),
    }


def make_plan(scene: str, *, seeds: list[int], backend: str, threads: int, iterations: int,
              arms: list[str] | None = None) -> list[dict[str, Any]]:
    chosen = ablation_arms()
    unknown = sorted(set(arms or []) - set(chosen))
    if unknown:
        raise SystemExit(f"unknown arms {', '.join(unknown)} (known: {', '.join(chosen)})")
    base = {"lpips": True, "save_renders": False, "checkpoint_every": 0, "iterations": iterations,
            "backend": backend, "threads": threads}
    group = Path(scene).name
    return [{"name": f"{group}/{arm}/{backend}/seed{seed}", "group": group, "arm": arm, "seed": seed, "scene": scene,
             "config": {**base, "seed": seed, **overrides}}
            for seed in seeds for arm, overrides in chosen.items() if not arms or arm in arms]


def signed_distances(centres: Any, mesh: Any, samples: int = 4000) -> dict[str, float]:
    """Side of ``mesh`` (a trimesh) the points lie on: share above, median / p10 / p90 signed distance."""
    import numpy as np
    import trimesh

    rng = np.random.default_rng(0)
    points = centres[rng.choice(len(centres), min(samples, len(centres)), replace=False)].astype(np.float64)
    closest, distance, triangle = trimesh.proximity.closest_point(mesh, points)
    signed = np.sign(((points - closest) * mesh.face_normals[triangle]).sum(axis=1)) * distance
    p10, median, p90 = np.quantile(signed, [0.1, 0.5, 0.9])
    return {"above_share": float((signed > 0).mean()), "signed_median": float(median), "signed_p10": float(p10),
            "signed_p90": float(p90), "samples": int(len(points))}


def add_signed(result: Path, folders: list[Path], mesh_path: Path) -> int:
    """Add ``signed`` (per run name) to a merged device_study JSON."""
    import numpy as np
    import trimesh

    from esgs.core.io_utils import atomic_write_json

    mesh = trimesh.load(mesh_path, force="mesh")
    data = json.loads(result.read_text())
    signed = data.setdefault("signed", {})
    for folder in folders:
        rows = json.loads((folder / "rows.json").read_text())["rows"]
        centres = np.load(folder / "centres.npz")
        for row in rows:
            key = f"r{row['index']:03d}"
            if key in centres.files and len(centres[key]):
                signed[row["name"]] = signed_distances(centres[key], mesh)
                print(row["name"], signed[row["name"]])
    data["signed_command"] = " ".join(["benchmarks/esgs_prior_ablation.py signed", str(result),
                                       *map(str, folders), "--mesh", str(mesh_path)])
    atomic_write_json(result, data)
    return 0


def main(argv: list[str] | None = None) -> int:
    import sys

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["signed"]:
        parser = argparse.ArgumentParser(description="add the signed distances to a merged result")
        parser.add_argument("result", type=Path)
        parser.add_argument("folders", type=Path, nargs="+")
        parser.add_argument("--mesh", type=Path, required=True)
        args = parser.parse_args(argv[1:])
        return add_signed(args.result, args.folders, args.mesh)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("plan", type=Path)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--arms", nargs="+", default=None, help="a subset of the arms (default: all)")
    args = parser.parse_args(argv)
    plan = make_plan(args.scene, seeds=args.seeds, backend=args.backend, threads=args.threads,
                     iterations=args.iterations, arms=args.arms)
    args.plan.write_text(json.dumps(plan, indent=1))
    print(f"{len(plan)} runs -> {args.plan}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
