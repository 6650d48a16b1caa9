"""NDN inference cost per view (prints; not a test). Target: <= 2 s per view on this machine.

For each output size, one view's full inference path is timed: DDIM sampling of the depth
and normal states at the working resolution (the weights' saved recipe: DDIM steps x samples
per view), then the guided upsampling of depth and normals to the output size
(``maps_from_states``: bilinear + OpenCV guided filter + renormalisation). Views are sampled
as many per call as ``write_ndn_priors`` samples with its default ``batch_size``
(``views_per_batch``: one view per call with the shipped 5-sample recipe), so ``per view`` =
call time / views per call; ``--batch N`` adds a line for N views per call. The minimum over
repeats is reported, as wall time and as the process's CPU time: on the shared, overloaded 2-core machine the wall time of a one-thread
run is inflated by waiting for a core, while its CPU time is what an idle core would take.

    .venv/bin/python benchmarks/bench_ndn.py [--weights W] [--sizes 1920x1080 480x270]
        [--batch N] [--repeats 3] [--threads N] [--json OUT]

Weights that read evidence get SfM-like evidence (a point in every 20th pixel; its content does
not change the cost) and, with a sky head, their sky map is up-sampled too.

``--scene SCENE`` times what a user runs instead: ``write_ndn_priors`` on the scene's views end
to end (reading images and evidence, both shipped networks, upsampling, writing), once with the
default pair (depth network + normals network) and once with the depth network alone
(``--normal-weights same``), on a copy of the scene; seconds per view, wall and CPU.
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", default=None, help="default: the shipped weights")
    parser.add_argument("--sizes", nargs="+", default=["1920x1080", "480x270"])
    parser.add_argument("--batch", type=int, default=0,
                        help="also time N views per call (default: only what write_ndn_priors does)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (0 = torch's default)")
    parser.add_argument("--json", default=None, help="also write the lines as JSON here")
    parser.add_argument("--scene", default=None, help="time write_ndn_priors on this scene folder instead")
    args = parser.parse_args()
    if args.scene:
        return time_scene(args)

    import os

    import torch

    import inspect

    from esgs.core.ndn.infer import maps_from_states, upsample_probability, views_per_batch, write_ndn_priors
    from esgs.core.ndn.shipped import resolve_default_weights
    from esgs.core.ndn.train import load_checkpoint

    if args.threads:
        torch.set_num_threads(args.threads)
    weights = resolve_default_weights(args.weights)
    model, diffusion, config, _ = load_checkpoint(weights)
    working = config.model.working_size
    inference_batch = views_per_batch(inspect.signature(write_ndn_priors).parameters["batch_size"].default, diffusion)
    print(f"weights {weights} | DDIM steps {config.diffusion.sample_steps} x {config.diffusion.sample_ensemble} "
          f"samples ({config.diffusion.sample_reduce}) | {inference_batch} view(s) per call like write_ndn_priors "
          f"| working size {working}x{working * 9 // 16} | torch threads {torch.get_num_threads()} | load average {os.getloadavg()[0]:.1f}")
    rng = np.random.default_rng(0)
    height = working * 9 // 16
    lines = []
    for batch in sorted({inference_batch, args.batch or inference_batch}):
        views = torch.from_numpy(rng.uniform(-1, 1, (batch, 9, height, working)).astype(np.float32))
        evidence = None
        if config.model.evidence:
            from esgs.core.ndn.evidence import encode_evidence, evidence_reference

            points = torch.from_numpy(np.where(rng.uniform(0, 1, (batch, height, working)) < 0.05,
                                               rng.uniform(5, 50, (batch, height, working)), 0.0).astype(np.float32))
            evidence = encode_evidence(points, torch.zeros_like(points), evidence_reference(points),
                                       config.diffusion.log_depth_range)
        sample_times, sample_cpu = [], []
        for repeat in range(args.repeats):
            started, started_cpu = time.perf_counter(), time.process_time()
            depth, normal, sky = diffusion.sample(model, views, seed=repeat, evidence=evidence, return_sky=True)
            sample_times.append(time.perf_counter() - started)
            sample_cpu.append(time.process_time() - started_cpu)
        sample, cpu = min(sample_times) / batch, min(sample_cpu) / batch
        for size in args.sizes:
            width_px, height_px = (int(v) for v in size.split("x"))
            guide = rng.integers(0, 255, (height_px, width_px, 3), dtype=np.uint8)
            upsample_times, upsample_cpu = [], []
            for _ in range(args.repeats):
                started, started_cpu = time.perf_counter(), time.process_time()
                maps_from_states(depth[0, 0].numpy(), normal[0].numpy(), guide, kind=config.diffusion.depth_state,
                                 log_range=config.diffusion.log_depth_range)
                if sky is not None:
                    upsample_probability(sky[0, 0].numpy(), guide)
                upsample_times.append(time.perf_counter() - started)
                upsample_cpu.append(time.process_time() - started_cpu)
            upsample = min(upsample_times)
            total, total_cpu = sample + upsample, cpu + min(upsample_cpu)
            print(f"batch {batch} | {size:>9} | wall: sampling {sample:.3f} s/view + guided upsampling {upsample:.3f} s "
                  f"= {total:.3f} s per view | CPU time {total_cpu:.3f} s per view "
                  f"({'meets' if total_cpu <= 2.0 else 'misses'} the 2 s target on an idle core)")
            lines.append({"views_per_call": batch, "output_size": size, "wall_s_per_view": round(total, 4),
                          "cpu_s_per_view": round(total_cpu, 4), "sampling_wall_s": round(sample, 4),
                          "upsampling_wall_s": round(upsample, 4)})
    if args.json:
        import platform
        import sys

        from esgs.core.io_utils import atomic_write_json

        atomic_write_json(args.json, {"what": "NDN inference seconds per view (benchmarks/bench_ndn.py)",
                                      "command": " ".join(["python", *sys.argv]), "machine": platform.node(),
                                      "weights": str(weights), "threads": torch.get_num_threads(),
                                      "load_average": os.getloadavg()[0], "lines": lines})
    return 0


def time_scene(args: argparse.Namespace) -> int:
    """``--scene``: ``write_ndn_priors`` end to end, the shipped pair against the depth network alone."""
    import os
    import platform
    import shutil
    import sys
    import tempfile
    from pathlib import Path

    import torch

    from esgs.core.formats.scene_dir import SceneDir
    from esgs.core.io_utils import atomic_write_json
    from esgs.core.ndn.infer import write_ndn_priors
    from esgs.core.ndn.shipped import resolve_prior_networks

    if args.threads:
        torch.set_num_threads(args.threads)
    lines = []
    with tempfile.TemporaryDirectory() as folder:
        scene = Path(folder) / "scene"
        shutil.copytree(args.scene, scene)
        shutil.rmtree(SceneDir(scene).prior("ndn"), ignore_errors=True)
        views = len([p for p in SceneDir(scene).images.iterdir() if p.is_file()])
        for label, normal_weights in (("depth + normals networks (default)", None), ("depth network alone", "same")):
            networks = resolve_prior_networks(args.weights, normal_weights)
            best_wall = best_cpu = float("inf")
            for _ in range(args.repeats):
                started, started_cpu = time.perf_counter(), time.process_time()
                write_ndn_priors(scene, args.weights, normal_weights=normal_weights)
                best_wall = min(best_wall, (time.perf_counter() - started) / views)
                best_cpu = min(best_cpu, (time.process_time() - started_cpu) / views)
            print(f"{label}: {best_wall:.3f} s per view wall, {best_cpu:.3f} s CPU ({views} views, "
                  f"torch threads {torch.get_num_threads()}, load average {os.getloadavg()[0]:.1f})")
            lines.append({"networks": label, "depth_weights": str(networks.depth),
                          "normal_weights": str(networks.normals) if networks.normals else None, "views": views,
                          "wall_s_per_view": round(best_wall, 4), "cpu_s_per_view": round(best_cpu, 4)})
    if args.json:
        atomic_write_json(args.json, {"what": "write_ndn_priors seconds per view on a scene (benchmarks/bench_ndn.py "
                                              "--scene), the shipped pair against the depth network alone",
                                      "command": " ".join(["python", *sys.argv]), "machine": platform.node(),
                                      "scene": str(args.scene), "threads": torch.get_num_threads(),
                                      "load_average": os.getloadavg()[0], "lines": lines})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
