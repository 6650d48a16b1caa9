"""GPDFN cost against the rasterizer on the same realistic terrain Gaussians (prints; not a test).

For each count: GPDFN forward+backward (K fused Gaussians) and the CPU rasterizer's
RGB+depth+normal forward+backward at 480x270, measured side by side in one process,
minimum over repeats, and their ratio. The issue's budget: GPDFN at most 30 % of a
training step at 100k Gaussians.

    .venv/bin/python benchmarks/bench_gpdfn.py [--counts 10000 100000] [--fused-k 3] [--repeats 3]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_rasterizer import DEFAULT_MESH, oblique_camera, terrain_gaussians  # noqa: E402


def best_of(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[10000, 100000])
    parser.add_argument("--fused-k", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    args = parser.parse_args(argv)

    from esgs.core.gpdfn import GPDFN, GPDFNConfig
    from esgs.core.render import rasterization

    print(f"load average before: {os.getloadavg()[0]:.2f}; torch threads {torch.get_num_threads()}")
    print(f"{'Gaussians':>10} {'GPDFN ms':>10} {'raster ms':>10} {'GPDFN/raster':>13}")
    viewmats, Ks = oblique_camera(480, 270)
    for count in args.counts:
        scene = terrain_gaussians(count, args.mesh)
        raw = {"means": scene["means"].clone().requires_grad_(),
               "log_scales": scene["scales"].log().requires_grad_(),
               "quats": scene["quats"].clone().requires_grad_(),
               "opacity_logits": torch.logit(scene["opacities"]).requires_grad_(),
               "sh_dc": ((scene["colors"] - 0.5) / 0.28209479177387814).requires_grad_()}
        module = GPDFN(GPDFNConfig(fused_k=args.fused_k))
        for parameter in module.parameters():
            torch.nn.init.normal_(parameter, std=0.05)  # a trained module, not the zero start

        def gpdfn_step():
            out = module(**raw)
            (out["sh_dc"].sum() + out["opacity_logits"].sum() + out["log_scales"].sum()).backward()

        params = {k: scene[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "colors")}

        def raster_step():
            render, alpha, _ = rasterization(params["means"], params["quats"], params["scales"], params["opacities"],
                                             params["colors"], viewmats, Ks, 480, 270, render_depth=True,
                                             render_normals=True, backend="cpu")
            (render.sum() + alpha.sum()).backward()

        gpdfn_step(), raster_step()  # warm-up (Numba compile / cache load, voxel size)
        gpdfn_s, raster_s = best_of(gpdfn_step, args.repeats), best_of(raster_step, args.repeats)
        print(f"{count:>10,} {gpdfn_s * 1e3:>10.0f} {raster_s * 1e3:>10.0f} {gpdfn_s / raster_s:>13.2f}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
