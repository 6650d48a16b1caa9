"""Time writing and reading a 3DGS PLY of 1M Gaussians (SH degree 3). Prints the figures.

Target: reading 1M Gaussians in under 1 s. Run: .venv/bin/python benchmarks/bench_ply_io.py [N]
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from esgs.core.formats.ply import GaussianPly, read_gaussians_ply, write_gaussians_ply


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
    rng = np.random.default_rng(0)
    gaussians = GaussianPly(
        means=rng.normal(size=(n, 3)), normals=np.zeros((n, 3)), sh_dc=rng.normal(size=(n, 3)),
        sh_rest=rng.normal(size=(n, 15, 3)), opacity_logit=rng.normal(size=n),
        log_scales=rng.normal(size=(n, 3)), quats_wxyz=rng.normal(size=(n, 4)),
    )
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "bench.ply"
        start = time.perf_counter()
        write_gaussians_ply(path, gaussians)
        written = time.perf_counter() - start
        best = float("inf")
        for _ in range(3):
            start = time.perf_counter()
            read_gaussians_ply(path)
            best = min(best, time.perf_counter() - start)
        size_mb = path.stat().st_size / 1e6
    print(f"gaussians={n} sh_degree=3 file={size_mb:.1f} MB write={written:.3f} s read(best of 3)={best:.3f} s")


if __name__ == "__main__":
    main()
