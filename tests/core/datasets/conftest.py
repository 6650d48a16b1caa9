"""Synthetic panoramas shared by the dataset tests."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


def textured_panorama(width: int = 2048, seed: int = 0) -> np.ndarray:
    """[width/2, width, 3] uint8 equirectangular image of blotchy multi-scale noise (SIFT-friendly).

    The noise is wrapped in longitude (built by tiling) so the seam at +-180 degrees is invisible.
    """
    import cv2

    rng = np.random.default_rng(seed)
    height = width // 2
    image = np.zeros((height, width, 3), np.float32)
    for sigma, weight in ((1.5, 0.5), (4.0, 0.8), (12.0, 1.0)):
        noise = rng.standard_normal((height, width, 3)).astype(np.float32)
        tiled = np.concatenate([noise, noise, noise], axis=1)  # wrap-around blur
        blurred = cv2.GaussianBlur(tiled, (0, 0), sigma)[:, width : 2 * width]
        image += weight * blurred / blurred.std()
    image = 128.0 + 40.0 * image
    return np.clip(image, 0, 255).astype(np.uint8)


@pytest.fixture(scope="session")
def panorama_file(tmp_path_factory) -> Path:
    from esgs.core.formats.imageio import write_png

    path = tmp_path_factory.mktemp("panorama") / "pano.png"
    write_png(path, textured_panorama())
    return path


@pytest.fixture(scope="session")
def panorama_views(panorama_file, tmp_path_factory):
    """12 views 320x240 (60 deg, 50 % overlap) with exact cameras, cut from a textured panorama."""
    scene = tmp_path_factory.mktemp("views") / "scene"
    from esgs.core.datasets import PanoramaOptions, scene_from_panorama

    scene_from_panorama(panorama_file, scene, PanoramaOptions(width=320, height=240, fov_deg=60.0, overlap=0.5))
    return scene
