"""Image quality metrics for held-out views: PSNR and SSIM (:mod:`.image`) and LPIPS (:mod:`.lpips`).

Submodules are imported explicitly (``from esgs.core.metrics.image import psnr``) so that
``python -m esgs.core.metrics.lpips --fetch`` runs without importing torch twice.
"""
