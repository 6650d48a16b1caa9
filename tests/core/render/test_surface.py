"""The median surface of each pixel: which Gaussian the backends name, and the depth read from it."""
from __future__ import annotations

import math

import pytest
import torch

from esgs.core.errors import ConfigError
from esgs.core.priors.losses import depth_loss, normal_loss
from esgs.core.render import rasterization
from esgs.core.render.surface import median_surface_depth, median_surface_normals, median_surface_thinness
from tests.core.render.scenes import intrinsics, look_at_viewmat, random_scene


def _render(scene: dict, backend: str, **tensors):
    values = {name: tensors.get(name, scene[name]) for name in ("means", "quats", "scales", "opacities", "colors")}
    return rasterization(values["means"], values["quats"], values["scales"], values["opacities"], values["colors"],
                         scene["viewmats"], scene["Ks"], scene["width"], scene["height"], render_depth=True,
                         backend=backend)


def _crossing_by_hand(scene: dict, transmittance_margin: float = 1e-9) -> torch.Tensor:
    """[H, W] median ids by a plain loop over the reference backend's per-Gaussian alphas:
    composite the Gaussians one at a time (depth order) and note where T first drops to <= 1/2."""
    depth = (scene["means"] @ scene["viewmats"][0, :3, :3].T + scene["viewmats"][0, :3, 3])[:, 2]
    order = torch.argsort(depth, stable=True)
    transmittance = torch.ones(scene["height"], scene["width"], dtype=scene["means"].dtype)
    ids = torch.full((scene["height"], scene["width"]), -1, dtype=torch.long)
    for g in order.tolist():
        if depth[g] <= 0.01:
            continue
        only = torch.zeros_like(scene["opacities"])
        only[g] = scene["opacities"][g]
        _, alpha, _ = _render(scene, "reference", opacities=only)
        after = transmittance * (1.0 - alpha[0, :, :, 0])
        crossed = (ids < 0) & (transmittance > 0.5 + transmittance_margin) & (after <= 0.5 - transmittance_margin)
        ids[crossed] = g
        transmittance = after
    return ids


@pytest.mark.parametrize("seed", [0, 3])
def test_both_backends_name_the_gaussian_where_transmittance_crosses_one_half(seed):
    scene = random_scene(150, seed, width=36, height=28, opacity_range=(0.2, 0.95))
    _, alpha_cpu, meta_cpu = _render(scene, "cpu")
    _, alpha_ref, meta_ref = _render(scene, "reference")
    ids_cpu, ids_ref = meta_cpu["median_ids"][0], meta_ref["median_ids"][0]
    assert ids_cpu.shape == (28, 36) and ids_cpu.dtype == torch.long
    assert torch.equal(ids_cpu, ids_ref)
    # a median surface exists exactly where the pixel ends more than half covered
    assert torch.equal(ids_cpu >= 0, alpha_cpu[0, :, :, 0] >= 0.5)
    assert 0.2 < float((ids_cpu >= 0).float().mean()) < 1.0
    # and it is the Gaussian a one-at-a-time composite names (pixels far from T = 1/2 at a step)
    by_hand = _crossing_by_hand(scene, transmittance_margin=1e-6)
    decided = by_hand >= 0
    assert int(decided.sum()) > 100
    assert torch.equal(ids_cpu[decided], by_hand[decided])


def _flat_gaussian(normal_tilt_deg: float = 35.0, depth: float = 4.0, opacity: float = 0.99):
    """One wide, thin Gaussian 4 m in front of a camera at the origin looking along +y (world),
    its plane tilted about the world x axis."""
    tilt = math.radians(normal_tilt_deg)
    # the quaternion rotating z onto the plane normal (0, -cos, -sin): a rotation about x
    half = 0.5 * (math.pi / 2 + tilt)
    quat = torch.tensor([[math.cos(half), math.sin(half), 0.0, 0.0]], dtype=torch.float64)
    scene = {
        "means": torch.tensor([[0.1, depth, -0.05]], dtype=torch.float64),
        "quats": quat,
        "scales": torch.tensor([[1.5, 1.5, 0.002]], dtype=torch.float64),
        "opacities": torch.tensor([opacity], dtype=torch.float64),
        "colors": torch.ones(1, 3, dtype=torch.float64),
        "viewmats": look_at_viewmat((0.0, 0.0, 0.0), (0.0, 1.0, 0.0))[None],
        "Ks": intrinsics(40, 30)[None],
        "width": 40, "height": 30,
    }
    return scene


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_the_plane_depth_is_where_each_ray_meets_a_flat_gaussian(backend):
    scene = _flat_gaussian()
    _, alpha, meta = _render(scene, backend)
    ids = meta["median_ids"][0]
    assert int((ids == 0).sum()) > 200 and torch.equal(ids >= 0, alpha[0, :, :, 0] >= 0.5)
    viewmat, K = scene["viewmats"][0], scene["Ks"][0]
    depth, valid = median_surface_depth(ids, scene["means"], scene["quats"], scene["scales"], viewmat, K, kind="plane")
    assert torch.equal(valid, ids >= 0) and bool((depth[~valid] == 0).all())
    # the exact intersection of each pixel's ray with the plane, in the camera frame
    rotation, translation = viewmat[:3, :3], viewmat[:3, 3]
    centre = rotation @ scene["means"][0] + translation
    world_normal = torch.tensor([0.0, -math.cos(math.radians(35.0)), -math.sin(math.radians(35.0))],
                                dtype=torch.float64)
    normal = rotation @ world_normal
    rows, cols = torch.nonzero(valid, as_tuple=True)
    rays = torch.stack([(cols + 0.5 - K[0, 2]) / K[0, 0], (rows + 0.5 - K[1, 2]) / K[1, 1],
                        torch.ones(rows.shape[0], dtype=torch.float64)], -1)
    expected = (normal @ centre) / (rays @ normal)
    assert float((depth[valid] - expected).abs().max()) < 1e-6, float((depth[valid] - expected).abs().max())
    assert float(expected.max() - expected.min()) > 0.5  # the plane is far from fronto-parallel
    # the centre kind is the centre's depth at every pixel
    centre_depth, _ = median_surface_depth(ids, scene["means"], scene["quats"], scene["scales"], viewmat, K,
                                           kind="centre")
    assert torch.allclose(centre_depth[valid], centre[2].expand(int(valid.sum())))
    with pytest.raises(ConfigError, match="kind"):
        median_surface_depth(ids, scene["means"], scene["quats"], scene["scales"], viewmat, K, kind="mean")


def test_the_plane_depth_is_clamped_to_the_gaussian_near_edge_on_rays():
    scene = _flat_gaussian()
    ids = torch.zeros(30, 40, dtype=torch.long)
    viewmat, K = scene["viewmats"][0], scene["Ks"][0]
    edge_on = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)  # normal z: the plane holds the view axis
    edge_on_normal_view = median_surface_depth(ids, scene["means"], edge_on, scene["scales"], viewmat, K)[0]
    centre_z = float((viewmat[:3, :3] @ scene["means"][0] + viewmat[:3, 3])[2])
    reach = 3.0 * 1.5
    assert float(edge_on_normal_view.min()) >= centre_z - reach - 1e-9
    assert float(edge_on_normal_view.max()) <= centre_z + reach + 1e-9


def test_the_surface_depth_gradient_matches_finite_differences():
    scene = _flat_gaussian(normal_tilt_deg=20.0)
    _, _, meta = _render(scene, "cpu")
    ids = meta["median_ids"][0]
    viewmat, K = scene["viewmats"][0], scene["Ks"][0]
    weights = torch.rand(30, 40, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def loss(means, quats):
        return (median_surface_depth(ids, means, quats, scene["scales"], viewmat, K)[0] * weights).sum()

    assert torch.autograd.gradcheck(loss, (scene["means"].clone().requires_grad_(),
                                           scene["quats"].clone().requires_grad_()), eps=1e-6, atol=1e-5)


def test_a_median_depth_prior_moves_only_the_gaussian_at_the_surface():
    """A translucent Gaussian in front of an opaque one: the expected depth blends both, so a depth
    prior pulls on both; the median surface is the opaque one alone, and only it is pulled."""
    front = _flat_gaussian(depth=3.0, opacity=0.3, normal_tilt_deg=0.0)
    back = _flat_gaussian(depth=5.0, opacity=0.95, normal_tilt_deg=0.0)
    scene = dict(back)
    for name in ("means", "quats", "scales", "opacities", "colors"):
        scene[name] = torch.cat([front[name], back[name]])
    prior = torch.full((30, 40), 4.5, dtype=torch.float64)
    viewmat, K = scene["viewmats"][0], scene["Ks"][0]

    def gradients(kind: str) -> torch.Tensor:
        means = scene["means"].clone().requires_grad_()
        render, alpha, meta = _render(scene, "cpu", means=means)
        mask = torch.ones(30, 40, dtype=torch.bool)
        if kind == "expected":
            depth = render[0, :, :, meta["channels"]["depth"]][..., 0]
            loss = depth_loss(depth, prior, mask, alpha=alpha[0, :, :, 0])
        else:
            ids = meta["median_ids"][0]
            assert bool((ids[ids >= 0] == 1).all())  # the translucent front never takes T to 1/2
            depth, valid = median_surface_depth(ids, means, scene["quats"], scene["scales"], viewmat, K, kind=kind)
            loss = depth_loss(depth, prior, mask & valid)
        loss.backward()
        return means.grad

    expected = gradients("expected")
    assert float(expected[0].norm()) > 1e-3 and float(expected[1].norm()) > 1e-3
    for kind in ("plane", "centre"):
        median = gradients(kind)
        assert float(median[0].norm()) == 0.0
        assert float(median[1].norm()) > 1e-3


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_the_median_normal_is_the_surface_gaussians_axis_facing_the_camera(backend):
    scene = _flat_gaussian(normal_tilt_deg=35.0)
    render, alpha, meta = rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                        scene["colors"], scene["viewmats"], scene["Ks"], 40, 30,
                                        render_normals=True, backend=backend)
    ids = meta["median_ids"][0]
    viewmat = scene["viewmats"][0]
    normals, valid = median_surface_normals(ids, scene["means"], scene["quats"], scene["scales"], viewmat)
    assert torch.equal(valid, ids >= 0) and int(valid.sum()) > 200
    assert bool((normals[~valid] == 0).all())
    # the plane's normal (0, -cos, -sin) in the camera frame, turned to face the camera
    tilt = math.radians(35.0)
    expected = viewmat[:3, :3] @ torch.tensor([0.0, -math.cos(tilt), -math.sin(tilt)], dtype=torch.float64)
    centre = viewmat[:3, :3] @ scene["means"][0] + viewmat[:3, 3]
    if float(expected @ centre) > 0:
        expected = -expected
    assert torch.allclose(normals[valid], expected.expand(int(valid.sum()), 3), atol=1e-9)
    # the rasterizer composites the same normal, scaled by the pixel's alpha
    composited = render[0, :, :, meta["channels"]["normal"]]
    unit = composited[valid] / composited[valid].norm(dim=-1, keepdim=True)
    assert torch.allclose(unit, normals[valid], atol=1e-6)


def _tilted_disc_and_its_median_ids() -> tuple[dict, torch.Tensor, torch.Tensor]:
    """The 20-degree disc, its median ids on the cpu backend and its camera's viewmat."""
    scene = _flat_gaussian(normal_tilt_deg=20.0)
    _, _, meta = _render(scene, "cpu")
    return scene, meta["median_ids"][0], scene["viewmats"][0]


def test_the_median_normal_gradient_matches_finite_differences():
    scene, ids, viewmat = _tilted_disc_and_its_median_ids()
    weights = torch.rand(30, 40, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)

    def loss(quats):
        return (median_surface_normals(ids, scene["means"], quats, scene["scales"], viewmat)[0] * weights).sum()

    assert torch.autograd.gradcheck(loss, (scene["quats"].clone().requires_grad_(),), eps=1e-6, atol=1e-5)


def test_a_median_normal_prior_turns_the_surface_gaussian_and_moves_nothing():
    """The composited normal's loss reaches every Gaussian's mean and opacity through the blend;
    on the median surface's normal it reaches only the rotation of the Gaussian at the surface."""
    front = _flat_gaussian(depth=3.0, opacity=0.3, normal_tilt_deg=10.0)
    back = _flat_gaussian(depth=5.0, opacity=0.95, normal_tilt_deg=-25.0)
    scene = dict(back)
    for name in ("means", "quats", "scales", "opacities", "colors"):
        scene[name] = torch.cat([front[name], back[name]])
    viewmat = scene["viewmats"][0]
    prior = torch.zeros(30, 40, 3, dtype=torch.float64)
    prior[..., 2] = -1.0  # fronto-parallel: neither Gaussian agrees
    mask = torch.ones(30, 40, dtype=torch.bool)

    def gradients(kind: str) -> dict:
        leaves = {name: scene[name].clone().requires_grad_() for name in ("means", "quats", "opacities")}
        render, alpha, meta = rasterization(leaves["means"], leaves["quats"], scene["scales"], leaves["opacities"],
                                            scene["colors"], scene["viewmats"], scene["Ks"], 40, 30,
                                            render_normals=True, backend="cpu")
        if kind == "composited":
            loss = normal_loss(render[0, :, :, meta["channels"]["normal"]], prior, mask, alpha=alpha[0, :, :, 0])
        else:
            normals, valid = median_surface_normals(meta["median_ids"][0], leaves["means"], leaves["quats"],
                                                    scene["scales"], viewmat)
            loss = normal_loss(normals, prior, mask & valid)
        loss.backward()
        return {name: leaf.grad if leaf.grad is not None else torch.zeros_like(leaf) for name, leaf in leaves.items()}

    composited = gradients("composited")
    assert float(composited["means"].norm()) > 1e-6 and float(composited["opacities"].norm()) > 1e-6
    median = gradients("median")
    assert float(median["means"].norm()) == 0.0 and float(median["opacities"].norm()) == 0.0
    assert float(median["quats"][0].norm()) == 0.0  # the translucent front is not the surface
    assert float(median["quats"][1].norm()) > 1e-3


def test_thinness_is_the_variance_along_the_normal_over_the_mean_variance():
    scene = _flat_gaussian(normal_tilt_deg=35.0)
    viewmat = scene["viewmats"][0]
    ids = torch.zeros(2, 2, dtype=torch.long)
    ids[1, 1] = -1
    tilt = math.radians(35.0)
    plane_normal = viewmat[:3, :3] @ torch.tensor([0.0, -math.cos(tilt), -math.sin(tilt)], dtype=torch.float64)
    in_plane = viewmat[:3, :3] @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    normals = torch.stack([plane_normal, -plane_normal, in_plane, in_plane]).reshape(2, 2, 3)
    thick, valid = median_surface_thinness(ids, scene["quats"], scene["scales"], viewmat, normals)
    assert valid.tolist() == [[True, True], [True, False]]
    mean_variance = float((scene["scales"] ** 2).sum() / 3)
    assert thick[0, 0] == pytest.approx(0.002 ** 2 / mean_variance)  # across the disc, either sign
    assert thick[0, 1] == pytest.approx(0.002 ** 2 / mean_variance)
    assert thick[1, 0] == pytest.approx(1.5 ** 2 / mean_variance)  # along the disc
    assert float(thick[1, 1]) == 0.0
    ball = median_surface_thinness(ids, scene["quats"], torch.ones(1, 3, dtype=torch.float64), viewmat, normals)[0]
    assert torch.allclose(ball[valid], torch.ones(3, dtype=torch.float64))


def test_the_thinness_gradient_matches_finite_differences_and_reaches_rotation_and_scales():
    scene, ids, viewmat = _tilted_disc_and_its_median_ids()
    normals = torch.randn(30, 40, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    scales = torch.tensor([[1.5, 0.9, 0.3]], dtype=torch.float64)

    def loss(quats, scales):
        return median_surface_thinness(ids, quats, scales, viewmat, normals)[0].sum()

    assert torch.autograd.gradcheck(loss, (scene["quats"].clone().requires_grad_(), scales.clone().requires_grad_()),
                                    eps=1e-6, atol=1e-5)
