"""PGSR: planar Gaussians, unbiased depth, its single- and multi-view losses, and a short run."""
from __future__ import annotations

import json
import math

import pytest
import torch

from esgs.core.config import config_to_dict
from esgs.core.errors import ConfigError
from esgs.core.methods import PGSRConfig, get_method, method_names, train, train_config_from_dict
from esgs.core.train.losses import flattening_loss
from esgs.core.render.surface import gaussian_normals
from esgs.core.methods.baselines.pgsr import (apply_homography, depth_to_normals, edge_weights,
                                              multi_view_losses, neighbour_views,
                                              normalised_cross_correlation, pixel_rays, plane_features,
                                              plane_homography, relative_pose, single_view_loss, unbiased_depth)
from esgs.core.render import rasterization
from esgs.core.train.config import TrainConfig
from esgs.core.train.hooks import TrainHook
from tests.core.train.scene import look_at, make_scene

DOUBLE = torch.float64


def _rotation_x(degrees: float) -> torch.Tensor:
    angle = math.radians(degrees)
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=DOUBLE)


def _quat_x(degrees: float) -> torch.Tensor:
    half = math.radians(degrees) / 2
    return torch.tensor([[math.cos(half), math.sin(half), 0.0, 0.0]], dtype=DOUBLE)


def _K(focal: float, width: int, height: int) -> torch.Tensor:
    return torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]], dtype=DOUBLE)


def _viewmat(eye, target) -> torch.Tensor:
    return torch.tensor(look_at(torch.tensor(eye).numpy(), torch.tensor(target).numpy(), up=(0.0, 1.0, 0.0)),
                        dtype=DOUBLE)


# --- per-Gaussian planes ------------------------------------------------------------------------
def test_the_normal_is_the_shortest_axis_facing_the_camera_and_the_distance_its_plane_offset():
    quats = torch.cat([_quat_x(40.0), _quat_x(0.0)])
    scales = torch.tensor([[0.3, 0.2, 0.01], [0.01, 0.5, 0.4]], dtype=DOUBLE)
    normals = gaussian_normals(quats, scales)
    torch.testing.assert_close(normals[0], _rotation_x(40.0)[:, 2])   # the rotated z axis
    torch.testing.assert_close(normals[1], torch.tensor([1.0, 0.0, 0.0], dtype=DOUBLE))
    means = torch.tensor([[0.0, 0.5, 3.0], [-1.0, 0.0, 2.0]], dtype=DOUBLE)
    features = plane_features(means, quats, scales, torch.eye(4, dtype=DOUBLE))
    # both normals face the camera at the origin: n . x < 0, and d = -n . x = |n . x|
    assert ((features[:, :3] * means).sum(-1) < 0).all()
    torch.testing.assert_close(features[:, 3], (normals * means).sum(-1).abs())
    torch.testing.assert_close(features[1], torch.tensor([1.0, 0.0, 0.0, 1.0], dtype=DOUBLE))
    # a camera moved by t sees the same plane at the distance measured from its own centre
    viewmat = torch.eye(4, dtype=DOUBLE)
    viewmat[:3, 3] = torch.tensor([0.0, 0.0, 1.0], dtype=DOUBLE)
    moved = plane_features(means, quats, scales, viewmat)
    torch.testing.assert_close(moved[:, 3], (normals * (means + viewmat[:3, 3])).sum(-1).abs())


def test_flattening_loss_is_the_mean_smallest_scale_over_the_extent():
    scales = torch.tensor([[0.3, 0.2, 0.01], [0.05, 0.5, 0.4]], dtype=DOUBLE, requires_grad=True)
    loss = flattening_loss(scales, extent=2.0)
    assert float(loss.detach()) == pytest.approx((0.01 + 0.05) / 2 / 2.0)
    loss.backward()
    expected = torch.zeros(2, 3, dtype=DOUBLE)
    expected[0, 2] = expected[1, 0] = 0.25
    torch.testing.assert_close(scales.grad, expected)
    assert torch.autograd.gradcheck(lambda s: flattening_loss(s, 3.0), (scales.detach().clone().requires_grad_(),))


# --- unbiased depth ---------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_unbiased_depth_of_one_oblique_flat_gaussian_is_the_ray_plane_intersection(backend):
    width, height = 24, 18
    K = _K(20.0, width, height)
    mean = torch.tensor([[0.1, -0.05, 3.0]], dtype=DOUBLE)
    quats, scales = _quat_x(50.0), torch.tensor([[1.5, 1.5, 1e-3]], dtype=DOUBLE)
    viewmat = torch.eye(4, dtype=DOUBLE)
    extra = plane_features(mean, quats, scales, viewmat)
    dtype = torch.float64 if backend == "reference" else torch.float32
    render, alpha, meta = rasterization(mean.to(dtype), quats.to(dtype), scales.to(dtype),
                                        torch.tensor([0.9], dtype=dtype), torch.ones(1, 3, dtype=dtype),
                                        viewmat.to(dtype)[None], K.to(dtype)[None], width, height,
                                        render_depth=True, extra=extra.to(dtype), backend=backend)
    planes = render[0, :, :, meta["channels"]["extra"]].to(DOUBLE)
    depth, valid = unbiased_depth(planes[..., :3], planes[..., 3], K)
    covered = alpha[0, :, :, 0] > 0.05
    assert int(covered.sum()) > 100 and bool(valid[covered].all())
    # the intersection of each pixel's ray r (z = 1) with the plane through the centre: z = (n . x) / (n . r)
    normal = _rotation_x(50.0)[:, 2]
    rays = pixel_rays(K, width, height)
    intersection = (normal @ mean[0]) / (rays @ normal)
    tolerance = 1e-9 if backend == "reference" else 2e-4
    torch.testing.assert_close(depth[covered], intersection[covered], rtol=tolerance, atol=tolerance)
    # the tilted plane spans a range of depths; the rasterizer's expected depth is the centre's z everywhere
    assert float(intersection[covered].max() - intersection[covered].min()) > 0.5
    expected_depth = render[0, :, :, meta["channels"]["depth"]][..., 0].to(DOUBLE)
    torch.testing.assert_close(expected_depth[covered], torch.full_like(expected_depth[covered], 3.0),
                               rtol=1e-4, atol=1e-4)


def test_unbiased_depth_hand_computed_pixel_and_invalid_pixels():
    K = _K(2.0, 2, 2)  # pixel (0, 0): ray (-0.25, -0.25, 1); pixel (1, 1): (0.25, 0.25, 1)
    normals = torch.zeros(2, 2, 3, dtype=DOUBLE)
    distances = torch.zeros(2, 2, dtype=DOUBLE)
    normals[0, 0] = torch.tensor([0.0, 0.6, -0.8]) * 0.5      # composited with alpha 0.5
    distances[0, 0] = 2.0 * 0.5
    normals[1, 1] = torch.tensor([0.0, 0.0, 1.0])              # faces away: no valid depth
    distances[1, 1] = 1.0
    depth, valid = unbiased_depth(normals, distances, K)
    # -n . r = -(0.6 * -0.25 - 0.8) = 0.95, z = 2 / 0.95
    assert float(depth[0, 0]) == pytest.approx(2.0 / 0.95)
    assert valid.tolist() == [[True, False], [False, False]]
    assert float(depth[1, 1]) == 0.0


# --- single view ------------------------------------------------------------------------------
def _plane_depth(normal, distance, K, width, height):
    rays = pixel_rays(K, width, height)
    return distance / -(rays @ normal)


def test_depth_normals_recover_the_plane_normal():
    width, height = 9, 7
    K = _K(8.0, width, height)
    normal = torch.tensor([0.3, -0.4, -0.866], dtype=DOUBLE)
    normal = normal / normal.norm()
    depth = _plane_depth(normal, 2.5, K, width, height)
    normals, ok = depth_to_normals(depth, K)
    assert ok.sum() == (width - 2) * (height - 2) and not ok[0].any() and not ok[:, -1].any()
    torch.testing.assert_close(normals[ok], normal.expand(int(ok.sum()), 3))


def test_edge_weights_hand_computed():
    row = torch.tensor([0.0, 0.0, 0.5, 1.0], dtype=DOUBLE)
    image = row[None, :, None].expand(3, 4, 3).clone()
    weights = edge_weights(image)
    # interior pixels (1, 1) and (1, 2): |dx| = 0.5 and 1.0, |dy| = 0 -> normalised 0 and 1
    expected = torch.zeros(3, 4, dtype=DOUBLE)
    expected[1, 1] = 1.0
    torch.testing.assert_close(weights, expected)


def test_single_view_loss_hand_computed_and_gradcheck():
    depth_normals = torch.zeros(1, 3, 3, dtype=DOUBLE)
    normals = torch.zeros(1, 3, 3, dtype=DOUBLE)
    depth_normals[0, 0] = torch.tensor([0.0, 0.0, -1.0])
    normals[0, 0] = torch.tensor([0.0, 0.6, -0.8])                  # |diff|_1 = 0.6 + 0.2 = 0.8
    depth_normals[0, 1] = torch.tensor([1.0, 0.0, 0.0])
    normals[0, 1] = torch.tensor([0.0, 1.0, 0.0])                   # |diff|_1 = 2
    normals[0, 2] = torch.tensor([5.0, 5.0, 5.0])                   # invalid: ignored
    weights = torch.tensor([[0.5, 0.25, 1.0]], dtype=DOUBLE)
    valid = torch.tensor([[True, True, False]])
    loss = single_view_loss(depth_normals, normals, weights, valid)
    assert float(loss) == pytest.approx((0.5 * 0.8 + 0.25 * 2.0) / 2)

    # the whole single-view chain, from the composited planes, against finite differences
    width, height = 6, 5
    K = _K(5.0, width, height)
    generator = torch.Generator().manual_seed(0)
    base = torch.tensor([0.1, -0.2, -1.0], dtype=DOUBLE)
    normal_map = (base + 0.1 * torch.randn(height, width, 3, generator=generator, dtype=DOUBLE)).requires_grad_()
    distance_map = (2.0 + 0.1 * torch.rand(height, width, generator=generator, dtype=DOUBLE)).requires_grad_()
    edge = torch.rand(height, width, generator=generator, dtype=DOUBLE)

    def chain(normal_map, distance_map):
        depth, valid = unbiased_depth(normal_map, distance_map, K)
        derived, ok = depth_to_normals(depth, K, valid)
        rendered = normal_map / normal_map.norm(dim=-1, keepdim=True)
        return single_view_loss(derived, rendered, edge, ok & valid)

    assert float(chain(normal_map, distance_map).detach()) > 0
    assert torch.autograd.gradcheck(chain, (normal_map, distance_map))


# --- two views --------------------------------------------------------------------------------
def _two_cameras():
    width, height = 32, 24
    K_ref, K_nb = _K(30.0, width, height), _K(26.0, width, height)
    viewmat_ref = _viewmat([0.0, 0.0, -4.0], [0.0, 0.0, 0.0])
    viewmat_nb = _viewmat([1.2, 0.3, -3.8], [0.1, 0.0, 0.0])
    return width, height, K_ref, K_nb, viewmat_ref, viewmat_nb


def _world_plane():
    normal = torch.tensor([0.2, 0.3, -1.0], dtype=DOUBLE)
    normal = normal / normal.norm()
    return normal, torch.tensor([0.05, -0.1, 0.3], dtype=DOUBLE)   # unit normal, a point on the plane


def _plane_in(viewmat, normal, point):
    """(n, d) of a world plane in a camera's frame, n facing the camera, n . X = -d."""
    n = viewmat[:3, :3] @ normal
    x = viewmat[:3, :3] @ point + viewmat[:3, 3]
    if float(n @ x) > 0:
        n = -n
    return n, -float(n @ x)


def test_plane_homography_agrees_with_explicit_reprojection():
    width, height, K_ref, K_nb, viewmat_ref, viewmat_nb = _two_cameras()
    normal, point = _world_plane()
    n_ref, d_ref = _plane_in(viewmat_ref, normal, point)
    rotation, translation = relative_pose(viewmat_ref, viewmat_nb)
    generator = torch.Generator().manual_seed(1)
    pixels = torch.rand(50, 2, generator=generator, dtype=DOUBLE) * torch.tensor([width, height], dtype=DOUBLE)
    H = plane_homography(K_ref, K_nb, rotation, translation, n_ref.expand(50, 3), torch.full((50,), d_ref,
                                                                                             dtype=DOUBLE))
    mapped, w = apply_homography(H, pixels[:, None, :])
    # explicit: back-project onto the plane in the world, then project into the neighbour
    rays_camera = torch.cat([pixels, torch.ones(50, 1, dtype=DOUBLE)], dim=-1) @ torch.linalg.inv(K_ref).T
    rotation_ref, t_ref = viewmat_ref[:3, :3], viewmat_ref[:3, 3]
    centre = -rotation_ref.T @ t_ref
    directions = rays_camera @ rotation_ref                       # R^T r, world frame
    steps = ((point - centre) @ normal) / (directions @ normal)
    world = centre + steps[:, None] * directions
    assert torch.allclose((world - point) @ normal, torch.zeros(50, dtype=DOUBLE), atol=1e-12)
    camera_nb = world @ viewmat_nb[:3, :3].T + viewmat_nb[:3, 3]
    projected = camera_nb @ K_nb.T
    expected = projected[:, :2] / projected[:, 2:]
    torch.testing.assert_close(mapped[:, 0], expected, rtol=1e-10, atol=1e-10)
    assert (w > 0).all()


def _consistent_maps(viewmat_nb, normal, point, width, height, *, alpha: float = 0.7):
    n_nb, d_nb = _plane_in(viewmat_nb, normal, point)
    normal_map = (alpha * n_nb).expand(height, width, 3).clone()
    distance_map = torch.full((height, width), alpha * d_nb, dtype=DOUBLE)
    return normal_map, distance_map


def test_forward_backward_error_vanishes_for_one_plane_and_grows_when_the_neighbour_disagrees():
    width, height, K_ref, K_nb, viewmat_ref, viewmat_nb = _two_cameras()
    normal, point = _world_plane()
    n_ref, d_ref = _plane_in(viewmat_ref, normal, point)
    pixels = torch.tensor([[16.5, 12.5], [10.5, 8.5], [20.5, 15.5]], dtype=DOUBLE)
    ref_normals = (0.6 * n_ref).expand(3, 3)                          # composited with alpha 0.6
    ref_distances = torch.full((3,), 0.6 * d_ref, dtype=DOUBLE)
    normal_map, distance_map = _consistent_maps(viewmat_nb, normal, point, width, height)
    result = multi_view_losses(pixels, ref_normals, ref_distances, normal_map, distance_map, K_ref, K_nb,
                               viewmat_ref, viewmat_nb)
    assert result["valid"].all()
    torch.testing.assert_close(result["error"], torch.zeros(3, dtype=DOUBLE), atol=1e-9, rtol=0)
    assert float(result["geo"]) == pytest.approx(0.0, abs=1e-9)
    torch.testing.assert_close(result["weight"], torch.ones(3, dtype=DOUBLE))
    # the neighbour's plane 2 cm further back: the round trip misses, by less than a pixel here
    shifted = distance_map + 0.7 * 0.02
    result = multi_view_losses(pixels, ref_normals, ref_distances, normal_map, shifted, K_ref, K_nb,
                               viewmat_ref, viewmat_nb)
    error = result["error"]
    assert (error > 1e-3).all() and (error < 1.0).all()
    assert float(result["geo"]) == pytest.approx(float((torch.exp(-error) * error).mean()))


def test_ncc_hand_cases():
    patch = torch.tensor([[0.1, 0.4, 0.2, 0.9]], dtype=DOUBLE)
    assert float(normalised_cross_correlation(patch, 2.0 * patch + 0.3)) == pytest.approx(1.0, abs=1e-6)
    assert float(normalised_cross_correlation(patch, -patch)) == pytest.approx(-1.0, abs=1e-6)
    # hand-computed: a = (-1, 1, 0), b = (0, 1, -1): sum ab = 1, |a|^2 = |b|^2 = 2 -> 0.5
    a = torch.tensor([[0.0, 2.0, 1.0]], dtype=DOUBLE)
    b = torch.tensor([[1.0, 2.0, 0.0]], dtype=DOUBLE)
    assert float(normalised_cross_correlation(a, b)) == pytest.approx(0.5, abs=1e-6)


def test_multi_view_losses_gradcheck():
    width, height, K_ref, K_nb, viewmat_ref, viewmat_nb = _two_cameras()
    normal, point = _world_plane()
    n_ref, d_ref = _plane_in(viewmat_ref, normal, point)
    generator = torch.Generator().manual_seed(2)
    pixels = torch.tensor([[15.5, 11.5], [12.5, 9.5], [18.5, 13.5], [14.5, 14.5]], dtype=DOUBLE)
    ref_normals = (0.8 * n_ref + 0.02 * torch.randn(4, 3, generator=generator, dtype=DOUBLE)).requires_grad_()
    ref_distances = (0.8 * d_ref + 0.01 * torch.randn(4, generator=generator, dtype=DOUBLE)).requires_grad_()
    normal_map, distance_map = _consistent_maps(viewmat_nb, normal, point, width, height, alpha=0.8)
    normal_map = (normal_map + 0.01 * torch.randn(height, width, 3, generator=generator, dtype=DOUBLE))
    distance_map = (distance_map + 0.01 * torch.randn(height, width, generator=generator, dtype=DOUBLE))
    ref_grey = torch.rand(height, width, generator=generator, dtype=DOUBLE)
    # the neighbour's image: the reference's content seen through the true plane (smoothly), plus noise
    nb_grey = (ref_grey + 0.2 * torch.rand(height, width, generator=generator, dtype=DOUBLE)).clamp(0, 1)

    def losses(ref_normals, ref_distances, normal_map, distance_map):
        result = multi_view_losses(pixels, ref_normals, ref_distances, normal_map, distance_map, K_ref, K_nb,
                                   viewmat_ref, viewmat_nb, ref_grey=ref_grey, neighbour_grey=nb_grey,
                                   patch_radius=1, error_threshold=5.0)
        assert result["valid"].all() and result["kept"].any()
        # the weights are constants of the step (detached, as in PGSR): the losses are linear in
        # the per-pixel error and NCC cost, which are what finite differences can check
        torch.testing.assert_close(result["geo"], (result["weight"] * result["error"]).sum() / 4)
        kept = result["kept"]
        torch.testing.assert_close(result["ncc"], (result["weight"] * result["cost"])[kept].mean())
        return result["error"], result["cost"]

    inputs = (ref_normals, ref_distances, normal_map.requires_grad_(), distance_map.requires_grad_())
    error, cost = losses(*inputs)
    assert (error > 0).all() and (cost > 0).any()
    assert torch.autograd.gradcheck(losses, inputs)


def test_neighbours_are_the_nearest_views_within_the_angle():
    class _View:
        def __init__(self, viewmat):
            self.viewmat = viewmat

    views = [_View(_viewmat([x, 0.0, -4.0], [x, 0.0, 0.0])) for x in (0.0, 0.5, 3.0)]
    views.append(_View(_viewmat([0.2, 0.0, -4.0], [0.2, 0.0, -8.0])))   # looks the other way
    neighbours = neighbour_views(views, count=2, max_angle_deg=30.0)
    assert neighbours[0] == [1, 2] and neighbours[1] == [0, 2] and neighbours[2] == [1, 0]
    assert neighbours[3] == [0]   # none within the angle: the nearest alone


# --- the method -------------------------------------------------------------------------------
def test_registry_lists_pgsr_and_its_config_round_trips_through_json(tmp_path):
    assert "pgsr" in method_names()
    method = get_method("pgsr")
    assert method.label == "PGSR" and method.settings_class is PGSRConfig
    settings = PGSRConfig(pgsr_flatten_weight=50.0, pgsr_multi_view_samples=512, pgsr_patch_radius=2)
    config = TrainConfig(scene=tmp_path, out=tmp_path / "run", method="pgsr", method_config=settings)
    text = json.dumps(config_to_dict(config))
    loaded = train_config_from_dict(json.loads(text))
    assert loaded.method == "pgsr" and loaded.method_config == settings
    with pytest.raises(ConfigError):
        PGSRConfig(pgsr_multi_view_samples=0).validate()
    with pytest.raises(ConfigError):
        PGSRConfig(pgsr_single_view_weight=-1.0).validate()


def test_the_train_command_and_the_bench_offer_pgsr(tmp_path):
    import argparse

    from esgs.core.commands import train as train_command
    from esgs.core.experiments.bench import METHODS

    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    args = parser.parse_args(["scene", "--out", str(tmp_path / "run"), "--method", "pgsr",
                              "--pgsr-flatten-weight", "10"])
    config = train_command.build_config(args)
    assert config.method == "pgsr" and config.method_config == PGSRConfig(pgsr_flatten_weight=10.0)
    row = next(method for method in METHODS if method.method == "pgsr")
    assert row.label == "PGSR" and not row.priors


class _Recorder(TrainHook):
    name = "recorder"

    def __init__(self):
        self.values = []
        self.extra_shapes = []

    def after_backward(self, run, context):
        self.values.append((context.step, float(context.loss.detach()), dict(context.loss_values)))
        extra = context.output.extra
        self.extra_shapes.append(None if extra is None else tuple(extra.shape))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("pgsr") / "scene", views=6, width=32, height=24)


def test_a_short_seeded_pgsr_run_lowers_its_loss(scene, tmp_path):
    recorder = _Recorder()
    # 40 steps: the warm-up of the geometric terms (7,000 of 30,000) ends at step 9
    config = TrainConfig(scene=scene, out=tmp_path / "run", iterations=40, backend="cpu", threads=1, lpips=False,
                         test_every=3, save_renders=False, checkpoint_every=0, progress_every=10, densify_until=0,
                         seed=3, method="pgsr", method_config=PGSRConfig(pgsr_multi_view_samples=256))
    result = train(config, hooks=[recorder])
    assert result.status == "completed"
    steps = {step: (loss, values) for step, loss, values in recorder.values}
    assert "pgsr_single_view" not in steps[8][1] and recorder.extra_shapes[7] is None
    for name in ("pgsr_flatten", "pgsr_single_view", "pgsr_multi_view_geo", "pgsr_multi_view_ncc"):
        assert name in steps[40][1] and math.isfinite(steps[40][1][name])
    assert recorder.extra_shapes[-1] == (24, 32, 4)
    assert any(values["pgsr_multi_view_geo"] > 0 for _, (_, values) in steps.items() if step_ok(values))
    early = sum(steps[s][0] for s in range(10, 15)) / 5
    late = sum(steps[s][0] for s in range(36, 41)) / 5
    assert late < early
    assert sum(steps[s][1]["l1"] for s in range(36, 41)) < sum(steps[s][1]["l1"] for s in range(1, 6))
    # the flattening loss pulled the smallest scales down
    assert steps[40][1]["pgsr_flatten"] < steps[1][1]["pgsr_flatten"]
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["method"] == "pgsr" and saved["method_config"]["pgsr_multi_view_samples"] == 256


def step_ok(values: dict) -> bool:
    return "pgsr_multi_view_geo" in values
