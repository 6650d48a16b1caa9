"""Pruning hidden Gaussians: each one's blending weight and share of light per view, and the strategy step."""
from __future__ import annotations

import pytest
import torch

from esgs.core.render import rasterization
from esgs.core.train.config import Schedule
from esgs.core.render.constants import NEAR_PLANE
from esgs.core.render.projection import project_gaussians
from esgs.core.train.contribution import Visibility, footprint, training_visibility
from esgs.core.train.gaussians import RenderParams
from esgs.core.train.strategy import DefaultStrategy, DefaultStrategySettings, StrategyContext
from tests.core.render.scenes import random_scene

from .test_densify import _model, _optimizer


def _params(scene: dict) -> RenderParams:
    return RenderParams(means=scene["means"], quats=scene["quats"], scales=scene["scales"],
                        opacities=scene["opacities"], colors=scene["colors"], sh_degree=None)


def _renderer(scene: dict, backend: str):
    """render(params, camera index) -> image [H, W, C], no background."""
    def render(params: RenderParams, camera: int) -> torch.Tensor:
        image, _, _ = rasterization(params.means, params.quats, params.scales, params.opacities, params.colors,
                                    scene["viewmats"][camera:camera + 1], scene["Ks"][camera:camera + 1],
                                    scene["width"], scene["height"], sh_degree=params.sh_degree, backend=backend)
        return image[0]
    return render


def _camera(scene: dict):
    return lambda camera: (scene["viewmats"][camera], scene["Ks"][camera], scene["width"], scene["height"])


def _projected(scene: dict, camera: int = 0) -> dict:
    projected = project_gaussians(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                  scene["viewmats"][camera:camera + 1], scene["Ks"][camera:camera + 1],
                                  scene["width"], scene["height"], near_plane=NEAR_PLANE, far_plane=1e10,
                                  antialiased=False, eps2d=0.3, need_normals=False)
    return {name: value[0] for name, value in projected.items() if isinstance(value, torch.Tensor)}


def _visibility(scene: dict, cameras, backend: str = "cpu") -> Visibility:
    return training_visibility(_params(scene), cameras, _renderer(scene, backend), _camera(scene))


def _alpha(scene: dict, camera: int, opacities: torch.Tensor) -> torch.Tensor:
    _, alpha, _ = rasterization(scene["means"], scene["quats"], scene["scales"], opacities, scene["colors"],
                                scene["viewmats"][camera:camera + 1], scene["Ks"][camera:camera + 1],
                                scene["width"], scene["height"], backend="reference")
    return alpha[0, :, :, 0]


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_summed_weights_are_each_gaussians_share_of_the_alpha_map(backend):
    scene = random_scene(60, 2, width=36, height=28, opacity_range=(0.2, 0.95))
    weights = _visibility(scene, [0], backend).weight
    assert weights.shape == (60,)
    # a pixel's blending weights add up to its alpha, so the Gaussians' sums add up to the alpha map's
    alpha = _alpha(scene, 0, scene["opacities"])
    assert float(weights.sum()) == pytest.approx(float(alpha.sum()), rel=1e-4)
    # alone in the view, a Gaussian's sum is its own alpha map's; behind others it can only be less
    for g in (0, 17, 41):
        only = torch.zeros_like(scene["opacities"])
        only[g] = scene["opacities"][g]
        alone = float(_alpha(scene, 0, only).sum())
        assert float(weights[g]) <= alone + 1e-4
    # both backends agree
    other = _visibility(scene, [0], "reference" if backend == "cpu" else "cpu").weight
    torch.testing.assert_close(weights, other, atol=1e-4, rtol=1e-4)


def test_the_footprint_is_the_summed_alpha_of_a_gaussian_alone_in_the_image():
    scene = random_scene(40, 5, width=64, height=48, scale_range=(0.05, 0.2), opacity_range=(0.2, 0.9))
    areas, on_screen = footprint(_projected(scene), 64, 48)
    u, v = _projected(scene)["means2d"].unbind(-1)
    assert torch.equal(on_screen, (u >= 0) & (u <= 64) & (v >= 0) & (v <= 48))
    errors = {"inside": [], "edge": []}
    for g in range(40):
        only = torch.zeros_like(scene["opacities"])
        only[g] = scene["opacities"][g]
        alone = float(_alpha(scene, 0, only).sum())
        if alone > 1.0:
            sigma = _projected(scene)["cov_diagonal"][g].sqrt()
            inside = bool(3 * sigma[0] < u[g] < 64 - 3 * sigma[0] and 3 * sigma[1] < v[g] < 48 - 3 * sigma[1])
            errors["inside" if inside else "edge"].append(abs(float(areas[g]) / alone - 1.0))
    # well inside: the integral, up to pixel sampling and the 1/255 alpha cut-off
    assert len(errors["inside"]) >= 20 and max(errors["inside"]) < 0.03
    # cut by the image's edge: the share inside, per axis (exact only for axis-aligned ellipses)
    assert len(errors["edge"]) >= 4 and max(errors["edge"]) < 0.25


def test_a_gaussian_behind_an_opaque_one_gets_one_per_cent_of_the_light_and_peaks_are_the_largest_view():
    scene = random_scene(2, 0, width=32, height=24, cameras=2)
    # Gaussian 0: a large, nearly opaque disc straight ahead of camera 0; Gaussian 1: a small one behind it
    scene["means"] = torch.tensor([[0.0, 3.0, 0.0], [0.0, 5.0, 0.0]], dtype=torch.float64)
    scene["quats"] = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=torch.float64)
    scene["scales"] = torch.tensor([[3.0, 0.05, 3.0], [0.2, 0.2, 0.2]], dtype=torch.float64)
    scene["opacities"] = torch.tensor([0.999, 0.9], dtype=torch.float64)
    per_view = [_visibility(scene, [camera]) for camera in (0, 1)]
    only = torch.tensor([0.0, 0.9], dtype=torch.float64)
    alone = float(_alpha(scene, 0, only).sum())
    assert alone > 5.0  # it would fill several pixels on its own
    # the disc's alpha is clamped at 0.99 (as in 3DGS): one per cent of the light passes it
    assert float(per_view[0].weight[1]) == pytest.approx(0.01 * alone, rel=0.02)
    assert float(per_view[0].light[1]) == pytest.approx(0.01, rel=0.1)
    assert float(per_view[0].light[0]) > 0.9  # nothing in front of the disc
    assert per_view[0].hidden(0.05).tolist() == [False, True]
    both = _visibility(scene, [0, 1])
    torch.testing.assert_close(both.weight, torch.maximum(per_view[0].weight, per_view[1].weight))
    torch.testing.assert_close(both.light, torch.maximum(per_view[0].light, per_view[1].light))


def test_a_gaussian_outside_every_image_is_unseen_not_hidden():
    scene = random_scene(2, 0, width=32, height=24)
    scene["means"] = torch.tensor([[0.0, 4.0, 0.0], [30.0, 4.0, 0.0]], dtype=torch.float64)  # the second far left/right
    visibility = _visibility(scene, [0])
    assert visibility.seen.tolist() == [True, False]
    assert float(visibility.light[1]) == 0.0 and float(visibility.weight[1]) == 0.0
    assert visibility.hidden(0.5).tolist() == [False, False]


def _strategy(threshold: float, light, *, densify_until: int = 10, iterations: int = 20, messages=None):
    model = _model([[-1.0] * 3] * 5, [0.5] * 5)
    optimizer = _optimizer(model)
    # no clone/split step anywhere (densify_from past densify_until), no opacity reset
    schedule = Schedule(iterations=iterations, sh_increase_every=5, densify_from=50, densify_until=densify_until,
                        densify_every=100, opacity_reset_every=0, position_lr_delay_steps=0)
    settings = DefaultStrategySettings(grad_threshold=2e-4, percent_dense=0.01, prune_opacity=0.005,
                                       max_screen_size_px=20.0, max_world_size=0.1, max_gaussians=1000,
                                       opacity_reset_value=0.01, spatial_order=False, prune_hidden=threshold)
    strategy = DefaultStrategy(settings, schedule)
    strategy.setup(StrategyContext(
        gaussians=model, optimizer=optimizer, extent=10.0, device=torch.device("cpu"),
        generator=torch.Generator().manual_seed(0), message=(messages.append if messages is not None else print),
        visibility=None if light is None else (lambda: Visibility(
            weight=torch.ones(5), seen=torch.tensor([True, True, True, True, False]),
            light=torch.tensor(light, dtype=torch.float32)))))
    strategy.state.max_radii = torch.arange(5, dtype=torch.float32)
    return model, optimizer, strategy


def test_the_end_of_densification_prunes_the_gaussians_hidden_in_every_view():
    messages: list[str] = []
    # Gaussian 4 is outside every image: unseen, kept whatever its light
    model, optimizer, strategy = _strategy(0.1, [0.02, 0.5, 0.099, 0.1, 0.0], messages=messages)
    means_before = model.params["means"].detach().clone()
    moments_before = optimizer.adam.state[model.params["means"]]["exp_avg"].clone()
    for step in range(1, 10):
        assert strategy.step_post_optimizer(step) == []
    (report,) = strategy.step_post_optimizer(10)
    assert (report.count_before, report.count_after, report.pruned) == (5, 3, 2)
    assert report.source_index.tolist() == [1, 3, 4]
    # parameters, Adam moments and the strategy's statistics move together
    torch.testing.assert_close(model.params["means"].detach(), means_before[[1, 3, 4]])
    torch.testing.assert_close(optimizer.adam.state[model.params["means"]]["exp_avg"], moments_before[[1, 3, 4]])
    assert strategy.state.max_radii.tolist() == [1.0, 3.0, 4.0]
    assert any("pruned 2 of 5 Gaussians hidden" in message for message in messages)
    assert strategy.step_post_optimizer(11) == []


@pytest.mark.parametrize("threshold, light, densify_until, iterations", [
    (0.0, [0.0] * 5, 10, 20),       # off
    (0.1, None, 10, 20),            # the caller cannot render
    (0.1, [0.0] * 5, 20, 20),       # densification lasts the whole run: nothing left to mend a prune
])
def test_no_pruning_of_hidden_gaussians_when_off_or_impossible(threshold, light, densify_until, iterations):
    model, _, strategy = _strategy(threshold, light, densify_until=densify_until, iterations=iterations)
    reports = [report for step in range(1, iterations + 1) for report in strategy.step_post_optimizer(step)]
    assert reports == [] and len(model) == 5


def test_a_threshold_that_would_prune_every_seen_gaussian_prunes_nothing_and_says_so():
    messages: list[str] = []
    model, _, strategy = _strategy(2.0, [0.2, 0.5, 0.99, 1.0, 0.0], messages=messages)
    (report,) = strategy.step_post_optimizer(10)
    assert report.pruned == 0 and len(model) == 5
    assert any("none pruned" in message for message in messages)


def test_training_prunes_at_the_end_of_densification_and_keeps_only_gaussians_the_light_reaches(fast_config):
    from esgs.core.train import TrainHook
    from esgs.core.train.trainer import Trainer

    class Watch(TrainHook):
        name = "watch"

        def __init__(self):
            self.reports, self.after = [], None

        def on_densify(self, run, report):
            self.reports.append(report)
            if report.pruned and self.after is None:
                self.after = run.training_visibility()

    # the tiny scene's overlapping plane Gaussians get 0.38-0.63 of the light at step 20: a
    # threshold of 0.45 calls about a tenth of them hidden
    threshold = 0.45
    watch = Watch()
    trainer = Trainer(fast_config(iterations=40, prune_hidden=threshold), hooks=[watch])
    trainer.run()
    until = trainer.schedule.densify_until
    pruning = [report for report in watch.reports if report.step == until and report.pruned]
    assert len(pruning) == 1 and pruning[0].count_after == pruning[0].count_before - pruning[0].pruned
    # removing Gaussians only uncovers the others: every one kept gets at least the threshold
    after = watch.after
    assert after is not None and bool(after.seen.all())
    assert float(after.light.min()) >= threshold
    assert len(trainer.gaussians) == pruning[0].count_after  # no densification after it
