"""Rasterizer speed and memory on a realistic terrain scene (prints a table; not a test).

Gaussians are fitted to the Mars landform surface (../shared/data/mars_landform): points
sampled uniformly on the mesh, flat Gaussians lying in the surface (shortest axis along the
face normal), tangent scales from the local neighbour spacing, seen by an oblique camera.
Each configuration renders RGB + expected depth + normals; "fwd" is a forward pass without
grad, "fwd+bwd" a forward with grad plus the backward of a fixed weighting of all channels.
Times are the minimum over the repeats: wall-clock ("ms") and process CPU time summed over
all threads ("cpu ms", the work done, which the load of a shared machine inflates much
less than the wall-clock time; on an idle machine wall ~ cpu / threads for the parallel
kernels; run with --threads 1 for a clean measure of the work, as spinning idle workers
count as CPU time too). "RSS MB" is the process's peak resident memory (torch included)
sampled during that configuration. The load average is printed before and after.

    .venv/bin/python benchmarks/bench_rasterizer.py [--counts 10000 100000 300000]
        [--resolutions 480x270 960x540] [--repeats 3] [--threads N] [--reference]
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from pathlib import Path

# Idle OpenMP workers (torch's and Numba's "omp" layer) spin by default; on a shared or
# busy machine the spinning steals the cores the other thread needs (measured: 3x the CPU
# time with 2 threads). Must be set before torch starts its OpenMP runtime.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MESH = REPO.parent / "shared" / "data" / "mars_landform" / "terrain_geometry.ply"


def terrain_gaussians(count: int, mesh_path: Path, seed: int = 0) -> dict:
    """Flat Gaussians on the terrain surface: means [N, 3], quats [N, 4], scales [N, 3], ..."""
    import trimesh
    from scipy.spatial import cKDTree

    from esgs.core.colmap.geometry import matrix_to_quat_wxyz

    mesh = trimesh.load(mesh_path, process=False)
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    normals = mesh.face_normals[faces]
    normals = np.where((normals[:, 2] < 0)[:, None], -normals, normals)
    distances, _ = cKDTree(points).query(points, k=4)
    spacing = distances[:, 1:].mean(axis=1)
    # Frame per point: tangent x, tangent y, normal z (the shortest axis).
    helper = np.where(np.abs(normals[:, 0:1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    tangent = np.cross(normals, helper)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    bitangent = np.cross(normals, tangent)
    frames = np.stack([tangent, bitangent, normals], axis=-1)
    quats = np.stack([matrix_to_quat_wxyz(frame) for frame in frames]) if count <= 20000 else \
        _quats_from_frames(frames)
    rng = np.random.default_rng(seed)
    scales = np.stack([spacing * 0.8, spacing * 0.8, spacing * 0.08], axis=-1) * rng.uniform(0.8, 1.2, (count, 1))
    heights = (points[:, 2] - points[:, 2].min()) / np.ptp(points[:, 2])
    colors = np.clip(np.stack([0.55 + 0.3 * heights, 0.35 + 0.2 * heights, 0.25 + 0.1 * heights], -1)
                     + rng.normal(0, 0.05, (count, 3)), 0, 1)
    return {
        "means": torch.from_numpy(points).float(), "quats": torch.from_numpy(quats).float(),
        "scales": torch.from_numpy(scales).float(),
        "opacities": torch.from_numpy(rng.uniform(0.6, 0.95, count)).float(),
        "colors": torch.from_numpy(colors).float(),
    }


def _quats_from_frames(frames: np.ndarray) -> np.ndarray:
    """Vectorised rotation matrix -> (w, x, y, z) for proper rotations (Shepperd's method, w-branch
    with a fallback through scipy when the trace is small)."""
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(frames).as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)


def oblique_camera(width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """World-to-camera [1, 4, 4] and K [1, 3, 3]: looking down at ~30 degrees over the crater."""
    eye = np.array([0.0, -170.0, 80.0])
    target = np.array([0.0, -10.0, -15.0])
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    view = np.eye(4)
    view[:3, :3] = rotation
    view[:3, 3] = -rotation @ eye
    focal = 0.5 * width / math.tan(math.radians(63.0) / 2)
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]])
    return torch.from_numpy(view).float()[None], torch.from_numpy(K).float()[None]


class PeakMemory:
    """Peak resident memory above the starting level, sampled from /proc every 2 ms."""

    def __init__(self):
        self.peak = 0
        self._running = False

    @staticmethod
    def rss() -> int:
        with open("/proc/self/statm") as handle:
            return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def __enter__(self):
        self.start = self.rss()
        self.peak = self.start
        self._running = True
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _sample(self):
        while self._running:
            self.peak = max(self.peak, self.rss())
            time.sleep(0.002)

    def __exit__(self, *exc):
        self._running = False
        self._thread.join()
        self.peak = max(self.peak, self.rss())

    @property
    def used(self) -> int:
        return self.peak - self.start


def run_once(scene, viewmats, Ks, width, height, backward: bool, backend: str):
    from esgs.core.render import rasterization

    inputs = {name: value.detach().clone().requires_grad_(backward) for name, value in scene.items()}
    start = time.perf_counter()
    start_cpu = time.process_time()
    with torch.set_grad_enabled(backward):
        render, alpha, meta = rasterization(inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"],
                                            inputs["colors"], viewmats, Ks, width, height, render_depth=True,
                                            render_normals=True, backend=backend)
        if backward:
            weights = torch.linspace(-1, 1, render.numel()).reshape(render.shape)
            ((render * weights).sum() + alpha.sum()).backward()
    return time.perf_counter() - start, time.process_time() - start_cpu, meta


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[10_000, 100_000, 300_000])
    parser.add_argument("--resolutions", nargs="+", default=["480x270", "960x540"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    parser.add_argument("--reference", action="store_true",
                        help="also time the dense reference at 10k Gaussians, 160x90 (slow)")
    args = parser.parse_args(argv)
    if not args.mesh.exists():
        print(f"mesh not found: {args.mesh}", file=sys.stderr)
        return 1
    import numba

    if args.threads:
        # Both pools: with fewer cores than busy threads, spinning workers inflate CPU time.
        numba.set_num_threads(args.threads)
        torch.set_num_threads(args.threads)
    print(f"load: {os.getloadavg()}  cores: {os.cpu_count()}  numba threads: {numba.get_num_threads()}  "
          f"torch threads: {torch.get_num_threads()}  OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}")
    # Compile (or load from the cache) before timing anything.
    warm = terrain_gaussians(2000, args.mesh)
    viewmats, Ks = oblique_camera(64, 36)
    run_once(warm, viewmats, Ks, 64, 36, True, "cpu")
    header = (f"{'N':>7} {'image':>8} {'in view':>7} {'pairs':>9} {'evals':>9} {'fwd ms':>8} {'cpu ms':>8} "
              f"{'fwd+bwd ms':>10} {'cpu ms':>8} {'Geval/s':>8} {'RSS MB':>8}")
    print(header)
    print("-" * len(header))
    for count in args.counts:
        scene = terrain_gaussians(count, args.mesh)
        for resolution in args.resolutions:
            width, height = (int(v) for v in resolution.split("x"))
            viewmats, Ks = oblique_camera(width, height)
            forward_times, forward_cpu, full_times, full_cpu = [], [], [], []
            with PeakMemory() as memory:
                for _ in range(args.repeats):
                    elapsed, cpu, meta = run_once(scene, viewmats, Ks, width, height, False, "cpu")
                    forward_times.append(elapsed)
                    forward_cpu.append(cpu)
                    elapsed, cpu, _ = run_once(scene, viewmats, Ks, width, height, True, "cpu")
                    full_times.append(elapsed)
                    full_cpu.append(cpu)
            in_view = (meta["radii"][0] > 0).float().mean().item()
            evaluations = meta["n_evaluations"][0]
            print(f"{count:>7} {resolution:>8} {in_view:>7.0%} {meta['n_intersections'][0]:>9} {evaluations:>9} "
                  f"{1e3 * min(forward_times):>8.1f} {1e3 * min(forward_cpu):>8.1f} "
                  f"{1e3 * min(full_times):>10.1f} {1e3 * min(full_cpu):>8.1f} "
                  f"{evaluations / min(forward_times) / 1e9:>8.3f} {memory.peak / 2**20:>8.0f}", flush=True)
    if args.reference:
        scene = terrain_gaussians(10_000, args.mesh)
        viewmats, Ks = oblique_camera(160, 90)
        cpu = min(run_once(scene, viewmats, Ks, 160, 90, True, "cpu")[0] for _ in range(args.repeats))
        reference = run_once(scene, viewmats, Ks, 160, 90, True, "reference")[0]
        print(f"10k at 160x90 fwd+bwd: cpu {1e3 * cpu:.1f} ms, reference {1e3 * reference:.0f} ms, "
              f"ratio {reference / cpu:.0f}x")
    print(f"load after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
