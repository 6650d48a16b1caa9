"""Random test scenes for the rasterizer tests (deterministic from a seed)."""
from __future__ import annotations

import math

import torch


def look_at_viewmat(eye, target, up=(0.0, 0.0, 1.0), dtype=torch.float64) -> torch.Tensor:
    """World-to-camera [4, 4] (OpenCV axes) for a camera at ``eye`` looking at ``target``."""
    eye = torch.tensor(eye, dtype=torch.float64)
    forward = torch.tensor(target, dtype=torch.float64) - eye
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, torch.tensor(up, dtype=torch.float64))
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rotation = torch.stack([right, down, forward])  # rows: camera axes in world
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = rotation
    view[:3, 3] = -rotation @ eye
    return view.to(dtype)


def intrinsics(width: int, height: int, fov_x_deg: float = 60.0, dtype=torch.float64) -> torch.Tensor:
    focal = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    return torch.tensor([[focal, 0, width / 2], [0, focal * 1.05, height / 2], [0, 0, 1]], dtype=dtype)


def random_scene(count: int, seed: int = 0, *, width: int = 40, height: int = 30, cameras: int = 1,
                 color_dims: int = 3, sh_degree: int | None = None, extra_dims: int = 0,
                 dtype=torch.float64, scale_range=(0.03, 0.4), opacity_range=(0.05, 0.95)) -> dict:
    """Gaussians scattered in front of cameras near the origin looking at +y."""
    generator = torch.Generator().manual_seed(seed)

    def uniform(*shape, low=0.0, high=1.0):
        return low + (high - low) * torch.rand(*shape, generator=generator, dtype=torch.float64)

    means = torch.stack([uniform(count, low=-2.5, high=2.5), uniform(count, low=2.0, high=7.0),
                         uniform(count, low=-1.8, high=1.8)], -1)
    quats = torch.randn(count, 4, generator=generator, dtype=torch.float64)
    log_low, log_high = math.log(scale_range[0]), math.log(scale_range[1])
    scales = torch.exp(uniform(count, 3, low=log_low, high=log_high))
    opacities = uniform(count, low=opacity_range[0], high=opacity_range[1])
    if sh_degree is None:
        colors = uniform(count, color_dims)
    else:
        colors = 0.3 * torch.randn(count, (sh_degree + 1) ** 2, 3, generator=generator, dtype=torch.float64)
    viewmats, Ks = [], []
    for cam in range(cameras):
        eye = (0.4 * cam, -0.5 * cam, 0.2 * cam)
        viewmats.append(look_at_viewmat(eye, (0.1 * cam, 4.0, 0.0)))
        Ks.append(intrinsics(width, height, 60.0 + 5 * cam))
    scene = {
        "means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
        "viewmats": torch.stack(viewmats), "Ks": torch.stack(Ks),
    }
    scene = {key: value.to(dtype) for key, value in scene.items()}
    scene["extra"] = uniform(count, extra_dims).to(dtype) if extra_dims else None
    scene["width"], scene["height"], scene["sh_degree"] = width, height, sh_degree
    return scene
