"""Many training runs at once on one machine (a GPU machine lent for minutes), measured where the mesh is.

A study is a plan: a JSON list of runs, each a scene folder (relative to the repository, so
it travels with the working tree), a TrainConfig dict (``backend`` cuda or cpu, ``method``,
``method_config``, ``iterations``, ``seed``...) and labels (``group``, ``arm``, ``seed``).
Three steps:

1. ``plan``: written by the study's own script or by hand (see ``example_plan`` below);
2. ``run PLAN --out DIR --workers N --deadline-s S``: trains the runs N at a time, each in
   a child process (one CUDA context each), and after every finished run rewrites
   ``DIR/rows.json`` (held-out PSNR / SSIM / LPIPS, Gaussians, seconds per step, peak memory,
   the sky error and per-view PSNR where the scene has gt masks) and ``DIR/centres.npz`` (the
   opaque centres of every run, one array per run): two files, so everything comes back from
   a machine that returns few files; runs not started by the deadline are listed as such;
3. ``merge DIR ... --json OUT``: here, where the meshes are: each run's centres against its
   scene's ``mesh/ground_truth.ply`` (``--scene-root`` maps the plan's relative scene paths to
   folders with meshes), then the summary over seeds per group and arm.

    python benchmarks/device_study.py run PLAN.json --out $OUT --workers 8 --deadline-s 480
    python benchmarks/device_study.py merge DIR --scene-root .devcarry=/work/runs/acc23/scenes --json RESULT.json
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

# idle OpenMP threads spin by default and take the cores a busy machine's other runs need
# (docs/rasterizer.md, "Spinning OpenMP workers"); set before torch loads
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

SUMMARY_KEYS = ("psnr", "ssim", "lpips", "psnr_sky_views", "psnr_ground_views", "sky_mae", "distance_mean",
                "distance_median", "n_gaussians", "s_per_step")
SKY_VIEW_FRACTION = 0.01


def run_one(entry: dict[str, Any], run_dir: Path, row_path: Path) -> int:
    """Train one plan entry into ``run_dir``; write its row (and centres beside it)."""
    import torch

    from esgs.core.experiments.runs import RunTask, run_task
    from esgs.core.formats.ply import read_gaussians_ply
    from esgs.core.formats.run_dir import RunDir
    from esgs.core.formats.scene_dir import SceneDir

    scene = Path(entry["scene"])
    started = time.perf_counter()
    summary = run_task(RunTask(name=entry["name"], scene=scene, out=run_dir, config=entry["config"],
                               variant=entry.get("arm", ""), seed=entry.get("seed", 0),
                               scene_name=entry.get("group", ""), measure_render=False))
    row = {key: entry.get(key) for key in ("name", "group", "arm", "seed")}
    row.update({key: summary.get(key) for key in ("psnr", "ssim", "lpips", "n_gaussians", "train_s", "steps",
                                                   "peak_memory_mib", "status")})
    row["wall_s"] = time.perf_counter() - started
    row["s_per_step"] = summary["train_s"] / max(summary["steps"], 1)
    row["backend"] = entry["config"].get("backend", "auto")
    if torch.cuda.is_available():
        row["peak_gpu_mib"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
    if SceneDir(scene).has_prior_maps("gt", "mask"):
        sys.path.insert(0, str(Path(__file__).parent))
        from sky_study import sky_error

        row.update(sky_error(run_dir, scene))
    gaussians = read_gaussians_ply(RunDir(run_dir).point_cloud)
    keep = 1.0 / (1.0 + np.exp(-gaussians.opacity_logit.reshape(-1))) >= 0.5
    np.save(row_path.with_suffix(".npy"), gaussians.means[keep].astype(np.float32))
    row_path.write_text(json.dumps(row))
    return 0


def _write_results(out: Path, rows: list[dict], pending: list[str], failed: dict[str, str], started: float,
                   plan_path: Path) -> None:
    from esgs.core.io_utils import atomic_write_json

    arrays = {}
    for row in rows:
        centres = out / "work" / f"{row['index']:03d}.npy"
        if centres.is_file():
            arrays[f"r{row['index']:03d}"] = np.load(centres)
    tmp = out / "centres.tmp.npz"
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, out / "centres.npz")
    atomic_write_json(out / "rows.json", {"plan": str(plan_path), "elapsed_s": time.time() - started, "rows": rows,
                                          "not_started": pending, "failed": failed,
                                          "environment": _environment()})


def _environment() -> dict[str, Any]:
    import platform

    import torch

    info = {"python": platform.python_version(), "torch": torch.__version__, "cpus": os.cpu_count()}
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    try:
        import gsplat

        info["gsplat"] = gsplat.__version__
    except ImportError:
        pass
    return info


def warm_up() -> float:
    """Build gsplat's kernels once, before the children start (each would build them at once)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_cuda import compile_gsplat

    return compile_gsplat()


def run_plan(plan_path: Path, out: Path, workers: int, deadline_s: float, grace_s: float = 150.0) -> int:
    """Run every entry of the plan, ``workers`` at a time; none starts after ``deadline_s``, and
    those still running ``grace_s`` later are stopped (their rows are lost: leave enough)."""
    plan = json.loads(plan_path.read_text())
    work = out / "work"
    work.mkdir(parents=True, exist_ok=True)
    started = time.time()
    if any(entry["config"].get("backend") == "cuda" for entry in plan):
        print(f"gsplat kernels: {warm_up()}", flush=True)
    queue = list(enumerate(plan))
    running: dict[int, tuple[subprocess.Popen, dict]] = {}
    rows: list[dict] = []
    failed: dict[str, str] = {}
    not_started: list[str] = []
    while queue or running:
        late = time.time() - started > deadline_s
        while queue and len(running) < workers and not late:
            index, entry = queue.pop(0)
            entry_path = work / f"{index:03d}.entry.json"
            entry_path.write_text(json.dumps(entry))
            log = open(work / f"{index:03d}.log", "w")
            process = subprocess.Popen([sys.executable, __file__, "one", str(entry_path), str(work / f"run{index:03d}"),
                                        str(work / f"{index:03d}.json")], stdout=log, stderr=subprocess.STDOUT)
            running[index] = (process, entry)
            print(f"[{time.time() - started:6.0f} s] start {entry['name']}", flush=True)
        if late and queue:
            print(f"[{time.time() - started:6.0f} s] deadline: {len(queue)} runs not started", flush=True)
            not_started = [entry["name"] for _, entry in queue]
            queue.clear()
        for index, (process, entry) in list(running.items()):
            if process.poll() is None:
                if time.time() - started > deadline_s + grace_s:
                    process.kill()
                continue
            del running[index]
            row_path = work / f"{index:03d}.json"
            if process.returncode == 0 and row_path.is_file():
                rows.append({"index": index, **json.loads(row_path.read_text())})
                print(f"[{time.time() - started:6.0f} s] done {entry['name']}: "
                      f"{rows[-1]['psnr']:.2f} dB, {rows[-1]['s_per_step']:.3f} s/step", flush=True)
            else:
                tail = (work / f"{index:03d}.log").read_text()[-1500:]
                failed[entry["name"]] = tail
                print(f"[{time.time() - started:6.0f} s] FAILED {entry['name']}\n{tail}", flush=True)
            pending = [e["name"] for _, e in queue] + [e["name"] for _, e in running.values()]
            _write_results(out, rows, pending, failed, started, plan_path)
        time.sleep(1.0)
    _write_results(out, rows, not_started, failed, started, plan_path)
    return 0


def merge(folders: list[Path], scene_roots: dict[str, str], target: Path) -> int:
    """Distances to each scene's mesh from the centres of the runs in ``folders``; summary over seeds."""
    from esgs.core.formats.scene_dir import SceneDir
    from esgs.core.io_utils import atomic_write_json
    from esgs.core.metrics.geometry import distance_statistics, load_mesh, point_to_mesh_distances

    rows, meshes, environments = [], {}, []
    for folder in folders:
        data = json.loads((folder / "rows.json").read_text())
        environments.append({"folder": str(folder), **data.get("environment", {}),
                             "not_started": data.get("not_started"), "failed": sorted(data.get("failed", {}))})
        centres = np.load(folder / "centres.npz")
        plan = json.loads(Path(data["plan"]).read_text()) if Path(data["plan"]).is_file() else None
        for row in data["rows"]:
            scene = plan[row["index"]]["scene"] if plan else None
            key = f"r{row['index']:03d}"
            if scene is not None and key in centres.files:
                for prefix, local in scene_roots.items():
                    if scene.startswith(prefix):
                        scene = local + scene[len(prefix):]
                mesh = SceneDir(Path(scene)).ground_truth_mesh
                if mesh.is_file():
                    if mesh not in meshes:
                        meshes[mesh] = load_mesh(mesh)
                    stats = distance_statistics(point_to_mesh_distances(centres[key].astype(np.float64), *meshes[mesh]))
                    row.update(distance_mean=stats["mean"], distance_median=stats["median"], distance_p95=stats["p95"],
                               distance_count=stats["count"])
            views = row.get("views") or []
            sky = [v["psnr"] for v in views if v["sky_fraction"] >= SKY_VIEW_FRACTION]
            ground = [v["psnr"] for v in views if v["sky_fraction"] < SKY_VIEW_FRACTION]
            row["psnr_sky_views"] = float(np.mean(sky)) if sky else None
            row["psnr_ground_views"] = float(np.mean(ground)) if ground else None
            rows.append(row)
    atomic_write_json(target, {"command": " ".join(sys.argv), "environments": environments, "rows": rows,
                               "summary": summarize(rows)})
    for name, figures in summarize(rows).items():
        print(name, {k: f"{v['mean']:.4g} ± {v['std']:.2g}" for k, v in figures.items()})
    return 0


def summarize(rows: list[dict]) -> dict[str, dict[str, dict[str, float]]]:
    """{"group/arm/backend": {figure: {mean, std, n}}} over seeds (sample std)."""
    groups: dict[str, list[dict]] = {}
    for row in rows:
        groups.setdefault(f"{row['group']}/{row['arm']}/{row.get('backend', 'auto')}", []).append(row)
    summary = {}
    for name, members in sorted(groups.items()):
        summary[name] = {}
        for key in SUMMARY_KEYS:
            values = [m[key] for m in members if m.get(key) is not None]
            if values:
                summary[name][key] = {"mean": float(np.mean(values)),
                                      "std": float(np.std(values, ddof=1)) if len(values) > 1 else 0.0,
                                      "n": len(values)}
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    one = sub.add_parser("one")
    one.add_argument("entry", type=Path)
    one.add_argument("run_dir", type=Path)
    one.add_argument("row", type=Path)
    run = sub.add_parser("run")
    run.add_argument("plan", type=Path)
    run.add_argument("--out", type=Path, required=True)
    run.add_argument("--workers", type=int, default=8)
    run.add_argument("--deadline-s", type=float, default=480, help="start no run after this many seconds")
    run.add_argument("--grace-s", type=float, default=150, help="then stop what still runs after this many more")
    combine = sub.add_parser("merge")
    combine.add_argument("folders", type=Path, nargs="+")
    combine.add_argument("--scene-root", action="append", default=[], help="PREFIX=LOCAL_FOLDER (repeat)")
    combine.add_argument("--json", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.command == "one":
        return run_one(json.loads(args.entry.read_text()), args.run_dir, args.row)
    if args.command == "run":
        return run_plan(args.plan, args.out, args.workers, args.deadline_s, args.grace_s)
    return merge(args.folders, dict(item.split("=", 1) for item in args.scene_root), args.json)


if __name__ == "__main__":
    sys.exit(main())
