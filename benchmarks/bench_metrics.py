"""Time PSNR, SSIM (forward and forward+backward) and LPIPS on CPU. Prints the figures.

Run: .venv/bin/python benchmarks/bench_metrics.py [WIDTH HEIGHT]   (default 480 270)
"""
from __future__ import annotations

import sys
import time

import torch

from esgs.core.metrics.image import psnr, ssim
from esgs.core.metrics.lpips import LPIPS, lpips_unavailable_reason


def best_of(function, repeats: int = 5) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    width, height = (int(sys.argv[1]), int(sys.argv[2])) if len(sys.argv) > 2 else (480, 270)
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(1, 3, height, width, generator=g)
    img = (ref + 0.05 * torch.randn(1, 3, height, width, generator=g)).clamp(0, 1).requires_grad_(True)

    def ssim_backward() -> None:
        img.grad = None
        (1 - ssim(img, ref)).backward()

    with torch.no_grad():
        t_psnr = best_of(lambda: psnr(img, ref))
        t_ssim = best_of(lambda: ssim(img, ref))
    t_ssim_bw = best_of(ssim_backward)
    print(f"{width}x{height} threads={torch.get_num_threads()}  psnr={t_psnr * 1e3:.2f} ms  "
          f"ssim={t_ssim * 1e3:.1f} ms  ssim forward+backward={t_ssim_bw * 1e3:.1f} ms")
    reason = lpips_unavailable_reason(download=False)
    if reason:
        print(f"lpips: skipped ({reason})")
        return
    model = LPIPS(download=False)
    with torch.no_grad():
        t_lpips = best_of(lambda: model(img, ref), repeats=3)
    print(f"{width}x{height} lpips={t_lpips * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
