"""The Numba projection (CPU backend) against the vectorised torch statement of the same maths
(which the CUDA mapping uses for normals): values and gradients."""
from __future__ import annotations

import pytest
import torch

from esgs.core.render.cpu import project
from esgs.core.render.projection import project_gaussians

from .helpers import relative_error
from .scenes import random_scene


@pytest.mark.parametrize("antialiased", [False, True])
def test_numba_projection_matches_torch(antialiased):
    scene = random_scene(300, seed=21, width=40, height=30, cameras=2)
    means = scene["means"].clone()
    means[:20, 1] *= -1  # some behind the cameras
    names = ("means", "quats", "scales", "opacities")
    results = []
    for function in (project, project_gaussians):
        inputs = {name: (means if name == "means" else scene[name]).clone().requires_grad_(True) for name in names}
        out = function(inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"], scene["viewmats"],
                       scene["Ks"], 40, 30, near_plane=0.05, far_plane=100.0, antialiased=antialiased, eps2d=0.3,
                       need_normals=True)
        valid = out["valid"]
        generator = torch.Generator().manual_seed(3)
        # Culled Gaussians' placeholder values differ between the two; only valid ones matter.
        loss = sum((torch.randn(out[key].shape, generator=generator, dtype=torch.float64)
                    * out[key] * (valid[..., None] if out[key].dim() == 3 else valid)).sum()
                   for key in ("means2d", "conics", "opacities", "depths", "normals"))
        loss.backward()
        results.append((out, {name: inputs[name].grad for name in names}))
    (numba_out, numba_grads), (torch_out, torch_grads) = results
    assert torch.equal(numba_out["valid"], torch_out["valid"])
    assert numba_out["valid"].sum() > 200
    valid = numba_out["valid"]
    for key in ("means2d", "conics", "opacities", "depths", "normals", "cov_diagonal"):
        assert torch.allclose(numba_out[key][valid], torch_out[key][valid], rtol=1e-10, atol=1e-10), key
    for name in names:
        assert relative_error(numba_grads[name], torch_grads[name]) < 1e-10, name


def test_project_points_by_hand_and_behind_the_camera():
    from esgs.core.render.projection import project_points

    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, 3] = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)  # camera frame = world + t
    K = torch.tensor([[100.0, 0.0, 32.0], [0.0, 80.0, 24.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    points = torch.tensor([[0.5, 1.0, 2.0], [0.0, 0.0, -2.0], [1.0, 1.0, -5.0]], dtype=torch.float64)
    u, v, z, in_front = project_points(points, viewmat, K, near_plane=0.01)
    # first point: camera (1, 0, 4) -> u = 100 * 1 / 4 + 32, v = 80 * 0 / 4 + 24
    assert in_front.tolist() == [True, False, False]
    assert float(z[0]) == 4.0 and float(u[0]) == 57.0 and float(v[0]) == 24.0
    # on the near plane and behind it: z is 1 and every value finite
    assert z[1:].tolist() == [1.0, 1.0] and bool(torch.isfinite(torch.stack([u, v])).all())
