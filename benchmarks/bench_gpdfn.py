"""GPDFN cost inside a training step, on realistic terrain Gaussians (prints; not a test).

The issue's budget: GPDFN costs at most 30 % of a training step at 100k Gaussians. For each
count this measures, side by side in one process (minimum over repeats, wall-clock and the
process CPU time):

- ``gpdfn``: GPDFN forward + backward alone (K fused Gaussians, a module with non-zero
  weights as after some training);
- ``step``: a full training step without GPDFN: activation of the raw parameters, the CPU
  rasterizer's RGB + depth + normal render at 480x270, the 3DGS photometric loss
  (0.8 L1 + 0.2 D-SSIM) plus an L1 depth-prior term, backward, and the fused Adam step over
  every Gaussian parameter (SH degree 3);
- ``step+gpdfn``: the same step with GPDFN's residuals applied before the render (the
  trainer hook's code path) and its weights in the Adam step.

``share`` = (step+gpdfn - step) / (step+gpdfn), GPDFN's part of a training step, printed
against the 30 % target, from the minimums and as the median over repeats of the share of
two steps run back to back (steadier when the load of a shared machine swings). The Gaussians move at every step (real Adam updates), so the
voxel-table reuse is exercised as in training.

``--order given morton`` (the default) measures every column twice, side by side with the
repeats interleaved: with the Gaussians in the order the surface sampler gives (random-like,
the order densification leaves without ``TrainConfig.spatial_order``) and sorted by the Morton
code of their centres (the trainer's order with ``spatial_order``, the default). Each order
has its own copy of the module, so each keeps its own voxel table as in training. The
``order`` line compares them: median over repeats of the back-to-back ratio.

``--every 2 4`` also prices an option that is NOT what the trainer does: running GPDFN
only every k-th step and adding its last (detached) residuals on the steps between. A step
with cached residuals is measured too, and the amortised share over k steps is printed as
``share@k``. It would change the method's training (the module and the Gaussians would get
GPDFN gradients on one step in k), so it is a measured proposal, not a setting.

    .venv/bin/python benchmarks/bench_gpdfn.py [--counts 10000 100000] [--fused-k 3]
        [--repeats 5] [--threads N] [--every 2 4] [--order given morton]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_rasterizer import DEFAULT_MESH, oblique_camera, terrain_gaussians  # noqa: E402

WIDTH, HEIGHT = 480, 270
TARGET_SHARE = 0.30
ORDERS = ("given", "morton")


def ordered(scene: dict, order: str) -> dict:
    """``scene`` as sampled ("given") or with every per-Gaussian tensor sorted by Morton code ("morton")."""
    if order == "given":
        return scene
    from esgs.core.train.spatial_order import spatial_order

    permutation = spatial_order(scene["means"])
    return {name: value[permutation].contiguous() for name, value in scene.items()}


def best_of(function, repeats: int) -> tuple[float, float]:
    """(minimum wall-clock seconds, minimum process CPU seconds) over ``repeats`` calls."""
    walls, cpus = [], []
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        function()
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    return min(walls), min(cpus)


def _model(scene: dict):
    from esgs.core.train.gaussians import GaussianModel, inverse_sigmoid, rgb_to_sh_dc

    count = scene["means"].shape[0]
    return GaussianModel.from_tensors(
        means=scene["means"], sh_dc=rgb_to_sh_dc(scene["colors"])[:, None, :], sh_rest=torch.zeros(count, 15, 3),
        opacity_logit=inverse_sigmoid(scene["opacities"]), log_scales=scene["scales"].log(), quats=scene["quats"],
        max_sh_degree=3)


def _optimizer(model, module):
    from esgs.core.train.optim import TrainOptimizer

    optimizer = TrainOptimizer()
    for name, lr in (("means", 1.6e-4), ("sh_dc", 2.5e-3), ("sh_rest", 1.25e-4), ("opacity_logit", 0.05),
                     ("log_scales", 5e-3), ("quats", 1e-3)):
        optimizer.add_group(name, model.params[name], lr, per_gaussian=True)
    if module is not None:
        optimizer.add_group("gpdfn", list(module.parameters()), 1e-3)
    return optimizer


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[10000, 100000])
    parser.add_argument("--fused-k", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=0, help="torch and Numba threads (0 = their default)")
    parser.add_argument("--every", type=int, nargs="*", default=[],
                        help="also price running GPDFN every k-th step with cached residuals in between")
    parser.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    parser.add_argument("--order", nargs="+", choices=ORDERS, default=list(ORDERS),
                        help="Gaussian orders to measure side by side: as sampled (random-like) and/or Morton-sorted")
    args = parser.parse_args(argv)

    from esgs.core.methods.esgs.gpdfn import GPDFN, GPDFNConfig
    from esgs.core.methods.esgs.gpdfn_hook import apply_residuals, fused_render_params
    from esgs.core.metrics.image import ssim_map
    from esgs.core.train.rendering import render_view

    if args.threads:
        import numba

        torch.set_num_threads(args.threads)
        numba.set_num_threads(args.threads)
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs; torch threads "
          f"{torch.get_num_threads()}; K = {args.fused_k}; {WIDTH}x{HEIGHT}; minimum of {args.repeats}")
    print(f"{'Gaussians':>10} {'gpdfn ms':>9} {'step ms':>8} {'step+gpdfn ms':>14} {'share':>6} "
          f"{'target':>7} | cpu ms: {'gpdfn':>6} {'step':>6} {'step+gpdfn':>10} {'share':>6}")
    viewmat, K = (matrix[0] for matrix in oblique_camera(WIDTH, HEIGHT))
    for count in args.counts:
        sampled = terrain_gaussians(count, args.mesh)
        torch.manual_seed(0)
        trained = GPDFN(GPDFNConfig(fused_k=args.fused_k))
        for parameter in trained.parameters():
            torch.nn.init.normal_(parameter, std=0.05)  # a trained module, not the zero start
        with torch.no_grad():
            reference = render_view(_model(sampled).render_params(3), viewmat, K, WIDTH, HEIGHT, render_depth=True,
                                    backend="cpu")
            target_image = (reference.image * 0.9 + 0.05).clamp(0, 1)
            target_depth = reference.depth * 1.01

        def make_variant(scene: dict) -> dict:
            """The measured functions of one Gaussian order, with their own copy of the module."""
            module, alone = (GPDFN(GPDFNConfig(fused_k=args.fused_k)) for _ in range(2))
            module.load_state_dict(trained.state_dict())
            alone.load_state_dict(trained.state_dict())  # its own voxel table: its inputs do not move
            raw = _model(scene).params
            gpdfn_inputs = {"means": raw["means"], "log_scales": raw["log_scales"], "quats": raw["quats"],
                            "opacity_logits": raw["opacity_logit"], "sh_dc": raw["sh_dc"].reshape(-1, 3)}

            def gpdfn_only():
                out = alone(**gpdfn_inputs)
                (out["sh_dc"].sum() + out["opacity_logits"].sum() + out["log_scales"].sum()).backward()

            def make_step(use_gpdfn: bool, cached: bool = False):
                model = _model(scene)
                optimizer = _optimizer(model, module if use_gpdfn and not cached else None)
                if cached:
                    with torch.no_grad():
                        raw_model = model.params
                        residual = module(raw_model["means"], raw_model["log_scales"], raw_model["quats"],
                                          raw_model["opacity_logit"], raw_model["sh_dc"].reshape(-1, 3))

                def step():
                    params = model.render_params(3)
                    if cached:
                        params = apply_residuals(model, params, residual)
                    elif use_gpdfn:
                        params = fused_render_params(module, model, params)
                    out = render_view(params, viewmat, K, WIDTH, HEIGHT, render_depth=True, render_normals=True,
                                      backend="cpu")
                    image = out.image
                    ssim = ssim_map(image.permute(2, 0, 1)[None], target_image.permute(2, 0, 1)[None]).mean()
                    loss = 0.8 * (image - target_image).abs().mean() + 0.2 * (1.0 - ssim) \
                        + 0.1 * (out.depth - target_depth).abs().mean()
                    loss.backward()
                    optimizer.step()
                    optimizer.zero_grad()
                return step

            return {"module": alone, "gpdfn_only": gpdfn_only, "plain": make_step(False),
                    "fused": make_step(True), "cached": make_step(True, cached=True),
                    "times": {"gpdfn": [], "plain": [], "fused": [], "cached": []}}

        variants = {order: make_variant(ordered(sampled, order)) for order in args.order}
        for variant in variants.values():  # warm-up (Numba compile / cache load)
            variant["gpdfn_only"](), variant["plain"](), variant["fused"](), variant["cached"]()
            variant["module"].zero_grad(set_to_none=True)
        # interleave everything (orders, and the steps with and without GPDFN) so a change of
        # machine load hits all alike; the order of the orders alternates between repeats
        for repeat in range(args.repeats):
            names = list(variants) if repeat % 2 == 0 else list(reversed(variants))
            for name in names:
                variant = variants[name]
                variant["times"]["gpdfn"].append(best_of(variant["gpdfn_only"], 1))
                variant["module"].zero_grad(set_to_none=True)
                variant["times"]["plain"].append(best_of(variant["plain"], 1))
                variant["times"]["fused"].append(best_of(variant["fused"], 1))
                if args.every:
                    variant["times"]["cached"].append(best_of(variant["cached"], 1))
        for name, variant in variants.items():
            times = variant["times"]
            gpdfn_wall, gpdfn_cpu = min(t[0] for t in times["gpdfn"]), min(t[1] for t in times["gpdfn"])
            plain, fused = times["plain"], times["fused"]
            plain_wall, plain_cpu = min(t[0] for t in plain), min(t[1] for t in plain)
            fused_wall, fused_cpu = min(t[0] for t in fused), min(t[1] for t in fused)
            share_wall = (fused_wall - plain_wall) / fused_wall
            share_cpu = (fused_cpu - plain_cpu) / fused_cpu
            # the two steps of one repeat ran back to back: their paired share is less exposed to
            # load swings of a shared machine than the ratio of two minimums
            paired_wall = statistics.median((f[0] - p[0]) / f[0] for p, f in zip(plain, fused))
            paired_cpu = statistics.median((f[1] - p[1]) / f[1] for p, f in zip(plain, fused))
            verdict = "met" if share_wall <= TARGET_SHARE else "over"
            print(f"{count:>10,} {gpdfn_wall * 1e3:>9.0f} {plain_wall * 1e3:>8.0f} {fused_wall * 1e3:>14.0f} "
                  f"{share_wall:>6.2f} {verdict:>7} | cpu ms: {gpdfn_cpu * 1e3:>6.0f} {plain_cpu * 1e3:>6.0f} "
                  f"{fused_cpu * 1e3:>10.0f} {share_cpu:>6.2f}   order: {name}", flush=True)
            print(f"{'':>10} paired share (median over repeats of back-to-back steps): wall {paired_wall:.2f}, "
                  f"cpu {paired_cpu:.2f}", flush=True)
            if args.every:
                cached = times["cached"]
                cached_wall, cached_cpu = min(t[0] for t in cached), min(t[1] for t in cached)
                print(f"{'':>10} step with cached residuals: {cached_wall * 1e3:.0f} ms (cpu {cached_cpu * 1e3:.0f} ms)")
                for every in args.every:
                    wall = (fused_wall + (every - 1) * cached_wall) / every
                    cpu = (fused_cpu + (every - 1) * cached_cpu) / every
                    print(f"{'':>10} share@{every}: GPDFN every {every} steps -> {wall * 1e3:.0f} ms per step, share "
                          f"{(wall - plain_wall) / wall:.2f} (cpu {cpu * 1e3:.0f} ms, share {(cpu - plain_cpu) / cpu:.2f})",
                          flush=True)
        if len(variants) == 2:
            # same repeat, back to back: morton / given, CPU time (the steadier clock on a loaded machine)
            given, morton = variants["given"]["times"], variants["morton"]["times"]
            ratios = {key: [m[1] / g[1] for g, m in zip(given[key], morton[key])] for key in ("gpdfn", "plain", "fused")}
            spread = {key: (statistics.median(r), min(r), max(r)) for key, r in ratios.items()}
            print(f"{'':>10} order: morton / given CPU time, median (min-max) over repeats: "
                  + ", ".join(f"{key} {m:.3f} ({lo:.3f}-{hi:.3f})" for key, (m, lo, hi) in spread.items()), flush=True)
    print(f"load average after: {os.getloadavg()[0]:.2f}  (target: GPDFN share <= {TARGET_SHARE:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
