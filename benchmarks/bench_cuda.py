"""The ``cuda`` backend (gsplat) against ``cpu`` on one machine: agreement and training.

Meant for a machine with an NVIDIA GPU and gsplat installed (gsplat compiles its CUDA code
on first use; the time that takes is recorded). In one run, side by side:

1. ``compile``: gsplat's first call (JIT build of its kernels), seconds;
2. ``train``: the same scene, seed and settings trained with ``--backend cuda`` and
   ``--backend cpu`` (all the machine's cores): held-out PSNR / SSIM, Gaussian count,
   training seconds, seconds per step, peak memory; optionally full ESGS on a prior source;
3. ``agreement``: the CPU run's Gaussians rendered by both backends on every held-out view
   (colour, alpha, expected depth: mean / max absolute difference, PSNR of one against the
   other) and the gradients of an L1 loss against the photo on one view (cosine similarity
   and relative L2 difference per parameter);
4. each run's opaque centres (opacity >= 0.5) as ``<run>_centres.npz`` beside the JSON, for
   distances to the true mesh measured where the mesh is.

Every step is timed and written to the JSON as it finishes; a step that fails records its
error and the script goes on. ``--deadline-s`` skips the optional steps that would start late.

    python benchmarks/bench_cuda.py --scene SCENE --iterations 600 --json OUT.json \\
        [--runs DIR] [--arms cuda-3dgs cpu-3dgs cuda-esgs cpu-esgs] [--seeds 0 1 2] [--esgs-priors gt] [--deadline-s 480]

Where the mesh is (the GPU machine had no copy of it), the JSON files and centre files of
one or more such runs are merged and the distances added::

    python benchmarks/bench_cuda.py --merge A.json B.json --mesh MESH --json benchmarks/results/cuda_vs_cpu.json
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Callable

# idle OpenMP threads spin by default and take the cores a busy machine's other runs need
# (docs/rasterizer.md, "Spinning OpenMP workers"); set before torch loads
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from esgs.core.formats.run_dir import RunDir  # noqa: E402

STARTED = time.monotonic()
GPU = torch.device("cuda")


def _write(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=str))
    os.replace(tmp, path)


def _step(results: dict, name: str, json_path: Path, action: Callable[[], Any]) -> Any:
    """Run ``action``, store its value (or its error) under ``name`` and save the JSON."""
    print(f"[{time.monotonic() - STARTED:6.1f} s] {name} ...", flush=True)
    tick = time.perf_counter()
    try:
        value = action()
        results[name] = value
    except Exception as error:  # noqa: BLE001 - a device check records every failure and goes on
        traceback.print_exc()
        value = None
        results[name] = {"error": f"{type(error).__name__}: {error}"}
    results.setdefault("step_seconds", {})[name] = round(time.perf_counter() - tick, 2)
    _write(json_path, results)
    print(f"[{time.monotonic() - STARTED:6.1f} s] {name}: {json.dumps(results[name], default=str)[:600]}", flush=True)
    return value


def environment() -> dict:
    info: dict[str, Any] = {"python": platform.python_version(), "torch": torch.__version__,
                            "cpus": os.cpu_count(), "cuda": torch.version.cuda}
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    try:
        import gsplat

        info["gsplat"] = gsplat.__version__
    except ImportError as error:
        info["gsplat"] = f"missing: {error}"
    return info


def compile_gsplat() -> dict:
    """gsplat's first rasterization builds its kernels: time it on a tiny scene."""
    from esgs.core.render import rasterization

    device = GPU
    means = torch.tensor([[0.0, 0.0, 3.0]], device=device)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device)
    scales = torch.full((1, 3), 0.2, device=device)
    opacities = torch.tensor([0.8], device=device)
    colors = torch.rand(1, 3, device=device)
    viewmats = torch.eye(4, device=device)[None]
    Ks = torch.tensor([[[20.0, 0.0, 16.0], [0.0, 20.0, 16.0], [0.0, 0.0, 1.0]]], device=device)
    tick = time.perf_counter()
    render, alpha, _ = rasterization(means, quats, scales, opacities, colors, viewmats, Ks, 32, 32, backend="cuda")
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    return {"first_call_s": round(time.perf_counter() - tick, 2), "centre_alpha": float(alpha[0, 16, 16, 0])}


def train_run(scene: Path, out: Path, backend: str, iterations: int, seed: int, threads: int,
              esgs_priors: str | None) -> dict:
    from esgs.core.methods import esgs_config, train
    from esgs.core.train import TrainConfig

    settings = dict(iterations=iterations, backend=backend, seed=seed, threads=threads, lpips=False,
                    checkpoint_every=0, save_renders=False)
    if esgs_priors:
        config = esgs_config(scene, out, esgs_priors, **settings)
    else:
        config = TrainConfig(scene=scene, out=out, **settings)
    if backend == "cuda" and torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()
    if Path(out).exists():  # a rerun trains afresh instead of refusing and measuring the old run
        import shutil

        shutil.rmtree(out)
    tick = time.perf_counter()
    result = train(config)
    wall_s = time.perf_counter() - tick
    metrics = result.metrics or {}
    row = {"backend": backend, "method": config.method, "status": result.status, "steps": result.step,
           "n_gaussians": result.n_gaussians, "psnr": metrics.get("psnr"), "ssim": metrics.get("ssim"),
           "train_s": round(result.elapsed_s, 2), "wall_s": round(wall_s, 2),
           "s_per_step": round(result.elapsed_s / max(result.step, 1), 4),
           "torch_threads": torch.get_num_threads()}
    if backend == "cuda" and torch.cuda.is_available():
        row["peak_gpu_mib"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
    return row


def save_centres(run_dir: Path, target: Path) -> dict:
    from esgs.core.formats.ply import read_gaussians_ply

    gaussians = read_gaussians_ply(RunDir(run_dir).point_cloud)
    keep = 1.0 / (1.0 + np.exp(-gaussians.opacity_logit.reshape(-1))) >= 0.5
    np.savez_compressed(target, centres=gaussians.means[keep].astype(np.float32))
    return {"file": target.name, "opaque": int(keep.sum()), "all": int(len(keep))}


def agreement(run_dir: Path) -> dict:
    """The run's Gaussians rendered by both backends on its held-out views (sky model left
    out: it is the same torch code on both), and the gradients of an L1 loss on one view."""
    import dataclasses

    from esgs.core.train.evaluate import load_run
    from esgs.core.train.rendering import render_view

    config, data, model, _, _ = load_run(run_dir)
    model.to(torch.device("cpu"))
    views = data.test or data.train[:3]
    cuda = GPU
    background = torch.tensor(config.background, dtype=torch.float32)
    rows = []
    with torch.no_grad():
        cpu_params = model.render_params(model.max_sh_degree)
        cuda_params = dataclasses.replace(cpu_params, **{
            field.name: getattr(cpu_params, field.name).to(cuda) for field in dataclasses.fields(cpu_params)
            if isinstance(getattr(cpu_params, field.name), torch.Tensor)})
        for view in views:
            a = render_view(cpu_params, view.viewmat, view.K, view.width, view.height, background=background,
                            backend="cpu", render_depth=True)
            b = render_view(cuda_params, view.viewmat.to(cuda), view.K.to(cuda), view.width, view.height,
                            background=background.to(cuda), backend="cuda", render_depth=True)
            image_b, alpha_b, depth_b = b.image.cpu(), b.alpha.cpu(), b.depth.cpu()
            image_diff = (a.image - image_b).abs()
            mse = float(((a.image.clamp(0, 1) - image_b.clamp(0, 1)) ** 2).mean())
            hit = (a.alpha[..., 0] > 0.5) & (alpha_b[..., 0] > 0.5)
            depth_a = a.depth[..., 0][hit]
            rows.append({"view": view.name, "image_mean_abs": float(image_diff.mean()),
                         "image_max_abs": float(image_diff.max()),
                         "alpha_mean_abs": float((a.alpha - alpha_b).abs().mean()),
                         "psnr_cuda_vs_cpu": float(-10 * np.log10(max(mse, 1e-12))),
                         "depth_rel_mean_abs": float(((depth_a - depth_b[..., 0][hit]).abs()
                                                      / depth_a.clamp_min(1e-6)).mean())})
    summary = {key: float(np.mean([row[key] for row in rows]))
               for key in ("image_mean_abs", "image_max_abs", "alpha_mean_abs", "psnr_cuda_vs_cpu",
                           "depth_rel_mean_abs")}
    return {"views": rows, "mean": summary, "gradients": _gradient_agreement(model, views[0], config, cuda)}


def _gradient_agreement(model, view, config, cuda: torch.device) -> dict:
    """Cosine similarity and relative L2 difference of d(L1)/d(raw parameter), cpu vs cuda."""
    from esgs.core.train.rendering import render_view

    grads = {}
    for backend, device in (("cpu", torch.device("cpu")), ("cuda", cuda)):
        model.to(device)
        for parameter in model.params.values():
            parameter.grad = None
        out = render_view(model.render_params(model.max_sh_degree), view.viewmat.to(device), view.K.to(device),
                          view.width, view.height, background=torch.tensor(config.background, device=device),
                          backend=backend)
        loss = (out.image - view.image_float(device)).abs().mean()
        loss.backward()
        grads[backend] = {name: p.grad.detach().cpu().double() for name, p in model.params.items()
                          if p.grad is not None}
    model.to(torch.device("cpu"))
    result = {}
    for name, cpu_grad in grads["cpu"].items():
        if name not in grads["cuda"]:
            continue
        a, b = cpu_grad.reshape(-1), grads["cuda"][name].reshape(-1)
        result[name] = {"cosine": float(torch.nn.functional.cosine_similarity(a, b, dim=0)),
                        "relative_l2": float((a - b).norm() / a.norm().clamp_min(1e-30))}
    return result


def merge(parts: list[Path], mesh: Path, target: Path) -> int:
    """One JSON from several runs' files, with each run's opaque centres measured against ``mesh``."""
    from esgs.core.metrics.geometry import distance_statistics, load_mesh, point_to_mesh_distances

    vertices, faces = load_mesh(mesh)
    merged: dict[str, Any] = {
        "what": "cuda (gsplat, version in each part's environment) vs cpu backend on one GPU machine, same scene, seeds and settings; "
                "distances: opaque centres (opacity >= 0.5) to the true mesh, metres",
        "command": "python benchmarks/bench_cuda.py --merge " + " ".join(str(part) for part in parts)
                   + f" --mesh {mesh} --json {target}",
        "setup": "gsplat installed from its PyPI wheel with TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 (JIT build on the "
                 "first call, see each part's compile); cpu runs use every core of the same machine",
        "parts": [], "runs": {}}
    for part in parts:
        data = json.loads(part.read_text())
        merged["parts"].append({key: data.get(key) for key in ("command", "environment", "compile", "step_seconds",
                                                               "total_s", "iterations", "seeds", "scene")})
        if merged.get("agreement") is None and isinstance(data.get("agreement"), dict) \
                and "error" not in data["agreement"]:
            merged["agreement"] = data["agreement"]
        for name, row in data.items():
            if not name.startswith("train_") or name.endswith("_centres") or not isinstance(row, dict):
                continue
            if "error" in row or "skipped" in row:  # kept apart: a later part may have run it
                merged.setdefault("not_run", {})[f"{part.name}:{name}"] = row
                continue
            centres_file = part.parent / f"{name}_centres.npz"
            if centres_file.is_file():
                centres = np.load(centres_file)["centres"].astype(np.float64)
                stats = distance_statistics(point_to_mesh_distances(centres, vertices, faces))
                row = {**row, "distance_mean": stats["mean"], "distance_median": stats["median"],
                       "distance_p95": stats["p95"], "distance_count": stats["count"]}
            merged["runs"][name] = row
    merged["mesh"] = str(mesh)
    _write(target, merged)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--merge", type=Path, nargs="+", default=None, help="JSON files of earlier runs to merge")
    parser.add_argument("--mesh", type=Path, default=None, help="with --merge: the true mesh for distances")
    parser.add_argument("--scene", type=Path)
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--runs", type=Path, default=Path("/tmp/bench_cuda_runs"))
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--arms", nargs="+", default=["cuda-3dgs", "cpu-3dgs"],
                        choices=("cuda-3dgs", "cpu-3dgs", "cuda-esgs", "cpu-esgs"),
                        help="backend-method pairs to train, in this order (esgs needs --esgs-priors)")
    parser.add_argument("--no-agreement", action="store_true", help="skip the rendering/gradient comparison")
    parser.add_argument("--esgs-priors", default=None, help="also train full ESGS on this prior source")
    parser.add_argument("--deadline-s", type=float, default=480.0,
                        help="optional steps that would start after this many seconds are skipped")
    args = parser.parse_args(argv)
    if args.merge:
        if args.mesh is None:
            parser.error("--merge needs --mesh")
        return merge(args.merge, args.mesh, args.json)
    if args.scene is None:
        parser.error("--scene is required")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.runs.mkdir(parents=True, exist_ok=True)
    threads = os.cpu_count() or 1
    results: dict[str, Any] = {
        "what": "cuda (gsplat) vs cpu backend on one machine: the same scene, seed and settings",
        "command": "python " + " ".join([sys.argv[0], *(argv if argv is not None else sys.argv[1:])]),
        "scene": str(args.scene), "iterations": args.iterations, "seeds": args.seeds}
    _step(results, "environment", args.json, environment)
    _step(results, "compile", args.json, compile_gsplat)
    plan = [(f"train_{arm.replace('-', '_')}_s{seed}", *arm.split("-"), seed) for seed in args.seeds for arm in args.arms]
    first = True
    for name, backend, method, seed in plan:
        run_dir = args.runs / name
        if not first and time.monotonic() - STARTED > args.deadline_s:
            results[name] = {"skipped": "deadline"}
            continue
        first = False
        priors = args.esgs_priors if method == "esgs" else None
        if method == "esgs" and not priors:
            parser.error("an esgs arm needs --esgs-priors")
        _step(results, name, args.json,
              lambda b=backend, p=priors, r=run_dir, s=seed: train_run(args.scene, r, b, args.iterations, s, threads, p))
        if RunDir(run_dir).point_cloud.is_file():
            _step(results, name + "_centres", args.json,
                  lambda r=run_dir, n=name: save_centres(r, args.json.parent / f"{n}_centres.npz"))
        if (backend == "cpu" and not args.no_agreement and "agreement" not in results
                and RunDir(run_dir).point_cloud.is_file()):
            _step(results, "agreement", args.json, lambda r=run_dir: agreement(r))
    results["total_s"] = round(time.monotonic() - STARTED, 1)
    _write(args.json, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
