"""The CPU backend against the dense reference: outputs, gradients, edge cases, determinism."""
from __future__ import annotations

import numba
import pytest
import torch

from esgs.core.errors import ConfigError
from esgs.core.render import rasterization

from .helpers import relative_error, run_backend
from .scenes import random_scene

FORWARD_TOLERANCE = 1e-5
GRADIENT_TOLERANCE = 1e-4


def assert_backends_agree(scene: dict, **options) -> tuple[dict, dict]:
    """CPU == reference (both float64): outputs to 1e-5, gradients to 1e-4 relative."""
    reference = run_backend(scene, "reference", **options)
    cpu = run_backend(scene, "cpu", **options)
    assert cpu["render"].shape == reference["render"].shape
    assert (cpu["render"] - reference["render"]).abs().max().item() <= FORWARD_TOLERANCE
    assert (cpu["alpha"] - reference["alpha"]).abs().max().item() <= FORWARD_TOLERANCE
    assert torch.equal(cpu["meta"]["radii"], reference["meta"]["radii"])
    assert torch.allclose(cpu["meta"]["depths"], reference["meta"]["depths"])
    for name, gradient in reference["grads"].items():
        assert torch.isfinite(cpu["grads"][name]).all(), name
        assert relative_error(cpu["grads"][name], gradient) <= GRADIENT_TOLERANCE, name
    assert relative_error(cpu["means2d_grad"], reference["means2d_grad"]) <= GRADIENT_TOLERANCE
    return reference, cpu


ALL_CHANNELS = dict(render_depth=True, render_normals=True)


@pytest.mark.parametrize("count, width, height, seed", [(1, 16, 16, 0), (60, 31, 17, 1), (400, 48, 36, 2)])
def test_random_scenes_match_reference(count, width, height, seed):
    scene = random_scene(count, seed=seed, width=width, height=height, extra_dims=2)
    reference, _ = assert_backends_agree(scene, **ALL_CHANNELS)
    assert reference["alpha"].max() > 0.1  # the scene is actually visible


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_spherical_harmonics_match_reference(sh_degree):
    scene = random_scene(80, seed=10 + sh_degree, width=24, height=20, sh_degree=sh_degree, cameras=2)
    assert_backends_agree(scene, render_depth=True)


def test_antialiased_mode_and_backgrounds_match_reference():
    scene = random_scene(150, seed=4, width=30, height=22, cameras=2, extra_dims=1)
    backgrounds = torch.tensor([[0.1, 0.2, 0.3], [0.9, 0.5, 0.0]], dtype=torch.float64)
    reference, cpu = assert_backends_agree(scene, antialiased=True, eps2d=0.5, backgrounds=backgrounds, **ALL_CHANNELS)
    plain = run_backend(scene, "cpu", backward=False, antialiased=True, eps2d=0.5, **ALL_CHANNELS)
    # The background reaches the colour channels only, weighted by 1 - alpha.
    expected = plain["render"].clone()
    expected[..., :3] += (1 - plain["alpha"]) * backgrounds[:, None, None, :]
    assert torch.allclose(cpu["render"], expected, atol=1e-12)


@pytest.mark.parametrize("tile_size, color_dims", [(4, 1), (8, 3), (16, 5)])
def test_tile_sizes_odd_image_sizes_and_feature_widths(tile_size, color_dims):
    scene = random_scene(120, seed=6, width=37, height=23, color_dims=color_dims)
    backgrounds = torch.linspace(0.1, 0.9, color_dims, dtype=torch.float64)[None]
    reference, _ = assert_backends_agree(scene, tile_size=tile_size, render_depth=True, backgrounds=backgrounds)
    assert reference["render"].shape[-1] == color_dims + 1


def test_behind_camera_outside_image_and_near_plane():
    scene = random_scene(150, seed=8, width=32, height=24, extra_dims=1)
    means = scene["means"].clone()
    means[:30, 1] = -means[:30, 1]  # behind the camera (which looks along +y)
    means[30:50, 0] += 12.0  # far to the side, outside the image
    means[50:60, 1] = 0.02  # just beyond the near plane, with huge footprints
    means[60:65, 1] = 0.005  # inside the near plane
    scene["means"] = means
    reference, cpu = assert_backends_agree(scene, near_plane=0.01, **ALL_CHANNELS)
    radii = cpu["meta"]["radii"][0]
    assert torch.all(radii[:30] == 0) and torch.all(radii[60:65] == 0)
    assert torch.all(cpu["grads"]["means"][:30] == 0)


def test_degenerate_huge_and_transparent_gaussians():
    scene = random_scene(120, seed=9, width=28, height=20, extra_dims=1)
    scales = scene["scales"].clone()
    scales[:10, 2] = 0.0  # flat discs
    scales[10:15] = 0.0  # points: only the screen-space dilation remains
    scales[15:18] = 25.0  # larger than the view
    opacities = scene["opacities"].clone()
    opacities[20:30] = 0.0
    opacities[30:35] = 1.0 / 255.0 * 0.999  # can never reach the cut-off
    opacities[35:40] = 1.0  # hits the 0.99 clamp
    scene["scales"], scene["opacities"] = scales, opacities
    reference, cpu = assert_backends_agree(scene, **ALL_CHANNELS)
    assert torch.all(cpu["meta"]["radii"][0, 20:35] == 0)
    assert torch.all(cpu["grads"]["colors"][20:35] == 0)
    # Antialiased mode: points get no opacity at all (det(cov) = 0).
    assert_backends_agree(scene, antialiased=True, render_depth=True)


def test_no_gaussians():
    scene = random_scene(0, seed=0, width=20, height=10, extra_dims=2)
    backgrounds = torch.tensor([[0.25, 0.5, 0.75]], dtype=torch.float64)
    for backend in ("cpu", "reference"):
        render, alpha, meta = rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                            scene["colors"], scene["viewmats"], scene["Ks"], 20, 10,
                                            backgrounds=backgrounds, extra=scene["extra"], backend=backend,
                                            **ALL_CHANNELS)
        assert render.shape == (1, 10, 20, 3 + 1 + 3 + 2)
        assert torch.all(alpha == 0)
        assert torch.all(render[..., :3] == backgrounds[0]) and torch.all(render[..., 3:] == 0)
        assert meta["means2d"].shape == (1, 0, 2) and meta["radii"].shape == (1, 0)


def test_several_cameras_and_screen_space_gradient():
    scene = random_scene(200, seed=12, width=36, height=27, cameras=3, extra_dims=1)
    reference, cpu = assert_backends_agree(scene, **ALL_CHANNELS)
    assert cpu["means2d_grad"].shape == (3, 200, 2)
    assert cpu["means2d_grad"].abs().sum() > 0
    assert meta_channels_are_consistent(cpu["meta"], color=3, extra=1)


def meta_channels_are_consistent(meta, color, extra) -> bool:
    channels = meta["channels"]
    return (channels["color"] == slice(0, color) and channels["depth"] == slice(color, color + 1)
            and channels["normal"] == slice(color + 1, color + 4)
            and channels["extra"] == slice(color + 4, color + 4 + extra))


@pytest.mark.parametrize("fast_mode", [True, pytest.param(False, marks=pytest.mark.slow)])
def test_cpu_gradients_match_finite_differences(fast_mode):
    """gradcheck of the whole CPU pipeline (Numba kernels in float64) on a tiny scene; fast
    mode compares random projections of the Jacobian, the slow one every entry."""
    scene = random_scene(5, seed=3, width=12, height=9, sh_degree=1, extra_dims=1, opacity_range=(0.2, 0.8),
                         scale_range=(0.4, 0.8))
    names = ("means", "quats", "scales", "opacities", "colors", "extra")

    def render(*tensors):
        values = dict(zip(names, tensors))
        image, alpha, _ = rasterization(values["means"], values["quats"], values["scales"], values["opacities"],
                                        values["colors"], scene["viewmats"], scene["Ks"], 12, 9, sh_degree=1,
                                        extra=values["extra"], antialiased=True, tile_size=4, backend="cpu",
                                        **ALL_CHANNELS)
        return image, alpha

    inputs = tuple(scene[name].clone().requires_grad_(True) for name in names)
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=fast_mode)


def test_float32_close_to_float64_reference():
    scene64 = random_scene(300, seed=13, width=40, height=30, extra_dims=1)
    scene32 = {key: value.float() if isinstance(value, torch.Tensor) else value for key, value in scene64.items()}
    reference = run_backend(scene64, "reference", **ALL_CHANNELS)
    cpu = run_backend(scene32, "cpu", **ALL_CHANNELS)
    difference = (cpu["render"].double() - reference["render"]).abs()
    # A pixel where float32 rounding flips the 1/255 cut-off differs by up to ~1/255 x value;
    # everything else agrees to float32 precision.
    assert difference.max().item() < 1e-2
    assert (difference > 1e-4).double().mean().item() < 1e-3
    for name, gradient in reference["grads"].items():
        assert relative_error(cpu["grads"][name].double(), gradient) <= 1e-3, name


def test_bit_identical_between_runs_and_thread_counts():
    scene = random_scene(1500, seed=14, width=64, height=48, extra_dims=1, dtype=torch.float32)
    default_threads = numba.get_num_threads()
    try:
        first = run_backend(scene, "cpu", **ALL_CHANNELS)
        second = run_backend(scene, "cpu", **ALL_CHANNELS)
        single = run_backend(scene, "cpu", num_threads=1, **ALL_CHANNELS)
    finally:
        numba.set_num_threads(default_threads)
    for other in (second, single):
        assert torch.equal(first["render"], other["render"])
        assert torch.equal(first["alpha"], other["alpha"])
        assert torch.equal(first["means2d_grad"], other["means2d_grad"])
        for name in first["grads"]:
            assert torch.equal(first["grads"][name], other["grads"][name]), name


def test_bad_input_raises_config_error():
    scene = random_scene(4, seed=0)
    arguments = [scene[name] for name in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")]
    with pytest.raises(ConfigError, match="quats"):
        rasterization(arguments[0], arguments[1][:, :3], *arguments[2:], 10, 10)
    with pytest.raises(ConfigError, match="backend"):
        rasterization(*arguments, 10, 10, backend="vulkan")
    with pytest.raises(ConfigError, match="dtype"):
        rasterization(arguments[0].float(), *arguments[1:], 10, 10)
    with pytest.raises(ConfigError, match="sh_degree"):
        rasterization(*arguments, 10, 10, sh_degree=1)
    with pytest.raises(ConfigError, match="float32 or float64"):
        rasterization(*[tensor.half() for tensor in arguments], 10, 10, backend="cpu")


def test_cuda_backend_is_optional():
    from esgs.core.render.cuda import cuda_available

    available, reason = cuda_available()
    if not available:
        scene = random_scene(4, seed=0)
        with pytest.raises(ConfigError, match="cuda"):
            rasterization(*[scene[name] for name in ("means", "quats", "scales", "opacities", "colors", "viewmats",
                                                     "Ks")], 10, 10, backend="cuda")
        pytest.skip(f"cuda backend unavailable here: {reason}")
    scene = {key: value.float().cuda() if isinstance(value, torch.Tensor) else value
             for key, value in random_scene(300, seed=1, width=48, height=32, dtype=torch.float32).items()}
    cuda = run_backend(scene, "cuda", backward=False, render_depth=True)
    cpu_scene = {key: value.cpu() if isinstance(value, torch.Tensor) else value for key, value in scene.items()}
    cpu = run_backend(cpu_scene, "cpu", backward=False, render_depth=True)
    assert (cuda["render"].cpu() - cpu["render"]).abs().mean() < 1e-2


def test_depth_order_is_a_stable_sort_with_ties():
    import numpy as np

    from esgs.core.render.cpu import _depth_order

    rng = np.random.default_rng(1)
    depth = rng.choice(np.array([0.5, 2.0, 2.5, 1e3], dtype=np.float32), 5000)
    depth[::7] = rng.uniform(0.02, 50.0, depth[::7].shape[0])
    index = np.flatnonzero(rng.random(5000) < 0.7)
    for values in (depth, depth.astype(np.float64)):
        expected = index[np.argsort(values[index], kind="stable")]
        assert np.array_equal(_depth_order(index, values), expected)


def test_gradient_descent_recovers_a_perturbed_scene():
    """The CPU gradients drive Adam from a perturbed scene back towards the target image."""
    target_scene = random_scene(60, seed=30, width=32, height=24, dtype=torch.float32)
    target = run_backend(target_scene, "cpu", backward=False, render_depth=True)["render"]
    generator = torch.Generator().manual_seed(31)
    parameters = {
        "means": (target_scene["means"] + 0.05 * torch.randn(60, 3, generator=generator)).requires_grad_(True),
        "colors": (target_scene["colors"] + 0.2 * torch.randn(60, 3, generator=generator)).requires_grad_(True),
        "log_scales": (target_scene["scales"].log() + 0.2 * torch.randn(60, 3, generator=generator)).requires_grad_(True),
    }
    optimizer = torch.optim.Adam(parameters.values(), lr=0.01)
    losses = []
    for _ in range(40):
        render, _, _ = rasterization(parameters["means"], target_scene["quats"], parameters["log_scales"].exp(),
                                     target_scene["opacities"], parameters["colors"], target_scene["viewmats"],
                                     target_scene["Ks"], 32, 24, render_depth=True, backend="cpu")
        loss = (render - target).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert all(map(lambda value: value == value, losses))  # no NaN
    assert losses[-1] < 0.5 * losses[0]


@pytest.mark.parametrize("antialiased", [False, True])
def test_float32_projection_storage_is_the_float64_storage_rounded_bit_for_bit(antialiased):
    # The projection kernels compute in float64 whatever their arrays hold; a float32 model's
    # Gaussians go in and its outputs and gradients come out in float32 (no float64 copies).
    # That must be exactly the old float64 storage rounded once, forward and backward.
    import numpy as np

    from esgs.core.render import cpu, projection_kernels
    from esgs.core.render import constants as K

    scene = random_scene(400, seed=21, width=48, height=36, cameras=2, dtype=torch.float32)
    scene["means"][:25, 1] = -3.0  # behind the cameras (they look along +y): culled
    scene["means"][25:40, 0] = 40.0  # far outside the image
    inputs = [scene[name].clone().requires_grad_() for name in ("means", "quats", "scales", "opacities")]
    settings = (48, 36, 0.01, 1e10, float(0.3 if antialiased else K.CLASSIC_DILATION), antialiased,
                float(K.JACOBIAN_MARGIN), True)
    outputs = cpu._Project.apply(*inputs, (scene["viewmats"], scene["Ks"], settings))
    generator = torch.Generator().manual_seed(3)
    upstream = [torch.randn(out.shape, generator=generator) for out in outputs[:5]]
    gradients = torch.autograd.grad(outputs[:5], inputs, upstream)

    wide = [t.detach().double().numpy() for t in inputs]
    views, Ks = scene["viewmats"].double().numpy(), scene["Ks"].double().numpy()
    cams, count = views.shape[0], 400
    shapes = [(cams, count, 2), (cams, count, 3), (cams, count), (cams, count), (cams, count, 3)]
    expected = [np.zeros(shape) for shape in shapes] + [np.empty((cams, count), np.bool_), np.empty((cams, count, 2))]
    projection_kernels.project_forward(*wide, views, Ks, *settings, *expected)
    assert expected[5].any() and not expected[5].all()  # some Gaussians culled, some kept
    for out, reference in zip(outputs, expected):
        assert torch.equal(out, torch.from_numpy(reference).to(out.dtype))
    expected_grads = [np.empty((count, 3)), np.empty((count, 4)), np.empty((count, 3)), np.empty(count)]
    projection_kernels.project_backward(*wide, views, Ks, *settings,
                                        *(g.double().numpy() for g in upstream), *expected_grads)
    for gradient, reference in zip(gradients, expected_grads):
        assert gradient.dtype == torch.float32
        assert torch.equal(gradient, torch.from_numpy(reference).float())
