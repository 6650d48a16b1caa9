"""Run a scene through a backend and collect outputs and gradients."""
from __future__ import annotations

import torch

from esgs.core.render import rasterization

PARAMETERS = ("means", "quats", "scales", "opacities", "colors", "extra")


def run_backend(scene: dict, backend: str, *, seed: int = 7, backward: bool = True, **options) -> dict:
    """Render ``scene`` with ``backend``; when ``backward``, back-propagate a fixed random
    weighting of every output channel and of alpha, and return the gradients too."""
    inputs = {name: scene[name].detach().clone().requires_grad_(backward)
              for name in PARAMETERS if scene.get(name) is not None}
    render, alpha, meta = rasterization(
        inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"], inputs["colors"],
        scene["viewmats"], scene["Ks"], scene["width"], scene["height"], sh_degree=scene.get("sh_degree"),
        extra=inputs.get("extra"), backend=backend, **options)
    result = {"render": render.detach(), "alpha": alpha.detach(), "meta": meta}
    if backward:
        generator = torch.Generator().manual_seed(seed)
        weights = torch.randn(render.shape, generator=generator, dtype=torch.float64).to(render.dtype)
        alpha_weights = torch.randn(alpha.shape, generator=generator, dtype=torch.float64).to(alpha.dtype)
        ((render * weights).sum() + (alpha * alpha_weights).sum()).backward()
        result["grads"] = {name: tensor.grad for name, tensor in inputs.items()}
        result["means2d_grad"] = meta["means2d"].grad
    return result


def relative_error(value: torch.Tensor, reference: torch.Tensor) -> float:
    scale = reference.norm().item()
    difference = (value - reference).norm().item()
    return difference / scale if scale > 0 else difference
