"""The sky model: behind the Gaussians, learned from every pixel, saved with the run, used by evaluation."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from esgs.core.errors import CheckpointError
from esgs.core.train.sky import SkyModel, composite, image_stride, load_sky, ray_directions, save_sky

from .conftest import train_then_checkpoint
from .scene import ground_truth_gaussians


def _true_sky() -> SkyModel:
    """A butterscotch sky, brighter towards +z: what the test scene's images show behind the plane."""
    sky = SkyModel(degree=1, initial_color=(0.75, 0.55, 0.35))
    with torch.no_grad():
        sky.coefficients[1] = torch.tensor([0.8, 0.8, 0.8])  # the band along z (basis order y, z, x)
    return sky


@pytest.fixture(scope="module")
def sky_scene(tiny_scene, tmp_path_factory):
    """The tiny plane scene with the true sky behind it and gt masks (255 = surface, 0 = sky)."""
    from esgs.core.colmap.io import read_model
    from esgs.core.formats.imageio import write_png
    from esgs.core.render import rasterization

    scene = tmp_path_factory.mktemp("sky") / "scene"
    shutil.copytree(tiny_scene, scene)
    truth, sky = ground_truth_gaussians(14, 0), _true_sky()
    model = read_model(scene / "sparse" / "0")
    (scene / "priors" / "gt" / "mask").mkdir(parents=True)
    for image in model.images.values():
        camera = model.cameras[image.camera_id]
        viewmat = torch.tensor(image.world_to_camera(), dtype=torch.float32)
        fx, fy, cx, cy = camera.params
        K = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]], dtype=torch.float32)
        render, alpha, _ = rasterization(truth["means"], truth["quats"], truth["scales"], truth["opacities"],
                                         truth["colors"], viewmat[None], K[None], camera.width, camera.height,
                                         backend="reference")
        with torch.no_grad():
            pixels = composite(render[0], alpha[0], sky.image(viewmat, K, camera.width, camera.height))
        write_png(scene / "images" / image.name, (pixels.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy())
        mask = np.where(alpha[0, :, :, 0].numpy() > 0.5, 255, 0).astype(np.uint8)
        write_png(scene / "priors" / "gt" / "mask" / image.name, mask)
    return scene


def test_directions_are_the_camera_axes_in_the_world():
    viewmat = torch.eye(4)
    viewmat[:3, :3] = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])  # world -> camera
    K = torch.tensor([[10.0, 0, 2.0], [0, 10.0, 2.0], [0, 0, 1.0]])
    directions = ray_directions(viewmat, K, 4, 4)
    assert directions.shape == (4, 4, 3)
    torch.testing.assert_close(directions.norm(dim=-1), torch.ones(4, 4))
    # the optical axis (camera +z) is world -x here; the image's +u (camera +x) is world +y
    centre = torch.nn.functional.normalize(directions[1:3, 1:3].mean(dim=(0, 1)), dim=0)
    torch.testing.assert_close(centre, torch.tensor([-1.0, 0.0, 0.0]), atol=1e-6, rtol=0)
    assert float(directions[0, 3, 1] - directions[0, 0, 1]) > 0


def test_sky_colour_gradients_match_finite_differences():
    sky = SkyModel(degree=3).double()
    with torch.no_grad():
        sky.base.copy_(torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64))
        sky.coefficients.copy_(0.3 * torch.randn(15, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64))
    directions = torch.nn.functional.normalize(torch.randn(7, 3, generator=torch.Generator().manual_seed(1),
                                                           dtype=torch.float64), dim=-1)
    assert torch.autograd.gradcheck(lambda base, bands: torch.func.functional_call(
        sky, {"base": base, "coefficients": bands}, (directions,)), (sky.base, sky.coefficients))


def test_the_sky_shows_only_where_the_gaussians_leave_the_pixel_transparent():
    image = torch.tensor([[[0.2, 0.1, 0.0], [0.0, 0.0, 0.0]]])  # premultiplied colours
    alpha = torch.tensor([[[1.0], [0.0]]])
    sky = torch.full((1, 2, 3), 0.6)
    torch.testing.assert_close(composite(image, alpha, sky), torch.tensor([[[0.2, 0.1, 0.0], [0.6, 0.6, 0.6]]]))
    uniform = SkyModel(degree=2, initial_color=(0.25, 0.5, 0.75))
    torch.testing.assert_close(uniform(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])),
                               torch.tensor([[0.25, 0.5, 0.75]] * 2))


def test_the_sky_file_round_trips_and_rejects_foreign_files(tmp_path):
    sky = _true_sky()
    path = save_sky(tmp_path / "sky.json", sky)
    again = load_sky(path)
    assert again.degree == 1 and torch.equal(again.base, sky.base) and torch.equal(again.coefficients, sky.coefficients)
    assert load_sky(tmp_path / "missing.json") is None
    (tmp_path / "other.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(CheckpointError, match="not a sky model"):
        load_sky(tmp_path / "other.json")


def _config(fast_config, scene, out, **values):
    return fast_config(**{"scene": scene, "out": out, "iterations": 60, "densify": False, "test_every": 5, **values})


def test_the_sky_is_learned_from_masked_pixels_and_evaluation_uses_it(fast_config, sky_scene, tmp_path):
    from esgs.core.train import train
    from esgs.core.train.evaluate import evaluate_run

    learned = train(_config(fast_config, sky_scene, tmp_path / "envmap"))
    plain = train(_config(fast_config, sky_scene, tmp_path / "none", sky="none"))
    assert (tmp_path / "envmap" / "sky.json").is_file() and not (tmp_path / "none" / "sky.json").exists()
    # the masks no longer drop the sky from the photometric loss: it is learned, and it shows
    from esgs.core.train.evaluate import load_run

    sky, truth = load_sky(tmp_path / "envmap" / "sky.json"), _true_sky()
    _, data, _, _, _ = load_run(tmp_path / "envmap")
    errors = []
    with torch.no_grad():
        for view in data.train:  # in the directions the training views saw sky
            directions = ray_directions(view.viewmat, view.K, view.width, view.height)[~view.mask[..., 0]]
            errors.append(float((sky(directions) - truth(directions)).abs().mean()))
    assert float(np.mean(errors)) < 0.05
    assert learned.metrics["psnr"] > plain.metrics["psnr"] + 3.0
    # re-evaluating the run folder composites the saved sky: the same figures as at the end of training
    again = evaluate_run(tmp_path / "envmap", use_lpips=False, save_renders=False)
    assert again["psnr"] == pytest.approx(learned.metrics["psnr"], abs=1e-4)
    (tmp_path / "envmap" / "sky.json").unlink()
    assert evaluate_run(tmp_path / "envmap", use_lpips=False, save_renders=False)["psnr"] < again["psnr"] - 3.0


def test_gaussians_are_kept_off_the_sky_where_the_masks_mark_it(fast_config, sky_scene, tmp_path):
    from esgs.core.train.trainer import Trainer

    def sky_alpha(weight: float) -> float:
        trainer = Trainer(_config(fast_config, sky_scene, tmp_path / f"w{weight}", sky_alpha_weight=weight))
        trainer.setup()
        assert ("sky_alpha" in {term.name for term in trainer.loss_terms}) == (weight > 0)
        for step in range(1, 61):
            trainer.train_step(step)
        values = []
        with torch.no_grad():
            for view in trainer.data.train:
                alpha = trainer.render(trainer.gaussians.render_params(0), view).alpha[..., 0]
                values.append(float(alpha[~view.mask[..., 0]].mean()))
        return float(np.mean(values))

    assert sky_alpha(1.0) < 0.8 * sky_alpha(0.0)


def test_the_ground_is_kept_opaque_where_the_masks_mark_surface(fast_config, sky_scene, tmp_path):
    from esgs.core.train.trainer import Trainer

    def surface_gap(weight: float) -> float:
        """Mean (1 - alpha) over the training views' surface pixels after 60 steps."""
        trainer = Trainer(_config(fast_config, sky_scene, tmp_path / f"s{weight}", surface_alpha_weight=weight))
        trainer.setup()
        assert ("surface_alpha" in {term.name for term in trainer.loss_terms}) == (weight > 0)
        for step in range(1, 61):
            trainer.train_step(step)
        gaps = []
        with torch.no_grad():
            for view in trainer.data.train:
                alpha = trainer.render(trainer.gaussians.render_params(0), view).alpha[..., 0]
                gaps.append(float(1.0 - alpha[view.mask[..., 0]].mean()))
        return float(np.mean(gaps))

    assert surface_gap(1.0) < 0.8 * surface_gap(0.0)


def test_a_resumed_run_continues_its_sky_exactly(fast_config, sky_scene, tmp_path):
    from esgs.core.train import train

    full = train(_config(fast_config, sky_scene, tmp_path / "full", iterations=16, checkpoint_every=8))
    first = _config(fast_config, sky_scene, tmp_path / "split", iterations=16, checkpoint_every=8)
    train_then_checkpoint(first, 8)
    resumed = train(_config(fast_config, sky_scene, tmp_path / "split", iterations=16, checkpoint_every=8,
                            resume=True))
    assert resumed.step == 16
    a, b = load_sky(tmp_path / "full" / "sky.json"), load_sky(tmp_path / "split" / "sky.json")
    assert torch.equal(a.base, b.base) and torch.equal(a.coefficients, b.coefficients)
    assert full.metrics["psnr"] == resumed.metrics["psnr"]


def test_runs_saved_before_the_sky_model_resume_without_one(fast_config, tiny_scene, tmp_path):
    from esgs.core.train import train
    from esgs.core.train.checkpoint import list_checkpoints
    from esgs.core.train.config import load_run_config

    config = fast_config(out=tmp_path / "old", iterations=8, checkpoint_every=4, sky="none")
    train(config)
    path = config.out / "config.json"
    data = json.loads(path.read_text())
    del data["sky"]  # an older run's files have no sky setting at all
    path.write_text(json.dumps(data))
    assert load_run_config(path).sky == "none"
    list_checkpoints(config.out / "checkpoints")[-1][1].unlink()
    resumed = train(fast_config(out=tmp_path / "old", iterations=8, checkpoint_every=4, sky="none", resume=True))
    assert resumed.status == "completed" and not (tmp_path / "old" / "sky.json").exists()


def test_the_legacy_switch_keeps_masked_pixels_out_of_the_loss_for_older_runs(fast_config, sky_scene, tmp_path):
    """Runs saved before the sky model resume as they trained: masked pixels out of the loss."""
    from esgs.core.train.config import run_config_from_dict
    from esgs.core.train.trainer import Trainer

    assert run_config_from_dict({"iterations": 5}).mask_photometric is True  # what older config.json files mean
    trainer = Trainer(_config(fast_config, sky_scene, tmp_path / "legacy", sky="none", mask_photometric=True))
    trainer.setup()
    view = trainer.data.train[0]
    view_mask = view.mask
    view.mask = torch.zeros_like(view_mask)  # every pixel masked: no photometric loss at all
    trainer.sampler.order = [0]
    assert trainer.train_step(1).loss.item() == pytest.approx(0.0, abs=1e-6)
    view.mask = view_mask


def test_a_mask_folder_of_another_name_is_not_taken_for_sky(fast_config, sky_scene, tmp_path):
    from esgs.core.train.trainer import Trainer

    scene = tmp_path / "scene"
    shutil.copytree(sky_scene, scene)
    shutil.copytree(scene / "priors" / "gt" / "mask", scene / "priors" / "mine" / "mask")
    trainer = Trainer(_config(fast_config, scene, tmp_path / "run", mask_source="mine"))
    trainer.setup()
    assert trainer.data.mask_source == "mine" and "sky_alpha" not in {t.name for t in trainer.loss_terms}


def test_renders_of_a_run_take_the_sky_that_goes_with_its_gaussians(fast_config, sky_scene, tmp_path):
    from esgs.core.train import train
    from esgs.core.train.evaluate import load_run_sky

    # no point_cloud.ply yet (a run stopped in its first session): the checkpoint's sky
    first = _config(fast_config, sky_scene, tmp_path / "stopped", iterations=16, checkpoint_every=8)
    train_then_checkpoint(first, 8)
    sky = load_run_sky(tmp_path / "stopped")
    assert sky is not None and not torch.equal(sky.base, SkyModel().base)
    # a run with sky none ignores a sky.json another run left in its folder
    plain = train(_config(fast_config, sky_scene, tmp_path / "plain", iterations=4, sky="none"))
    save_sky(plain.run_dir / "sky.json", _true_sky())
    assert load_run_sky(plain.run_dir) is None


def test_a_training_child_reads_a_partial_request_with_todays_defaults_and_writes_events_once(tiny_scene, tmp_path):
    from esgs.core.formats.run_dir import RunDir
    from esgs.core.methods.train_job import child_job
    from esgs.core.progress import JsonLinesProgress
    from esgs.core.runtime.child import ChildContext

    run = RunDir(tmp_path / "run")
    run.root.mkdir()
    events = JsonLinesProgress(run.events)
    data = {"scene": str(tiny_scene), "out": str(run.root), "iterations": 6, "backend": "reference", "threads": 1,
            "lpips": False, "progress_every": 2, "checkpoint_every": 0, "save_renders": False}
    try:
        child_job(data, ChildContext(progress=events, stop_file=None, config_path=tmp_path / "job.json",
                                     events_path=run.events))
    finally:
        events.close()
    saved = json.loads(run.config.read_text())
    assert saved["sky"] == "envmap" and saved["spatial_order"] is True and saved["mask_photometric"] is False
    steps = [json.loads(line)["step"] for line in run.events.read_text().splitlines()
             if json.loads(line).get("kind") == "progress" and json.loads(line).get("stage") == "train"]
    assert steps == sorted(set(steps)) and steps[-1] == 6


# --- the smoothness prior: the Dirichlet energy of the sky's logit field ---------------------

def _random_sky(degree: int = 3, seed: int = 0) -> SkyModel:
    sky = SkyModel(degree=degree).double()
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        sky.base.copy_(torch.randn(3, generator=generator, dtype=torch.float64))
        sky.coefficients.copy_(0.4 * torch.randn(sky.coefficients.shape, generator=generator, dtype=torch.float64))
    return sky


def _fibonacci_sphere(count: int) -> torch.Tensor:
    """[count, 3] near-uniform unit directions (equal-area cells: a quadrature weight of 4 pi / count each)."""
    index = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * index / count
    phi = index * np.pi * (3.0 - np.sqrt(5.0))
    radius = (1.0 - z * z).sqrt()
    return torch.stack([radius * phi.cos(), radius * phi.sin(), z], dim=-1)


def _surface_gradient_sq(sky: SkyModel, directions: torch.Tensor, step: float = 1e-4) -> torch.Tensor:
    """[P] |grad_S f|^2 summed over R, G, B, by central differences along two tangent axes at each direction."""
    helper = torch.where(directions[:, 2:].abs() < 0.9, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                         torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    first = torch.nn.functional.normalize(torch.linalg.cross(directions, helper), dim=-1)
    second = torch.linalg.cross(directions, first)
    total = torch.zeros(len(directions), dtype=torch.float64)
    with torch.no_grad():
        for tangent in (first, second):
            ahead = sky.logits(torch.nn.functional.normalize(directions + step * tangent, dim=-1))
            behind = sky.logits(torch.nn.functional.normalize(directions - step * tangent, dim=-1))
            total += ((ahead - behind) / (2.0 * step)).square().sum(dim=-1)
    return total


def test_the_dirichlet_energy_is_zero_for_a_uniform_sky_and_weights_each_band_by_l_l_plus_1():
    uniform = SkyModel(degree=3, initial_color=(0.7, 0.5, 0.3))
    assert float(uniform.dirichlet_energy().detach()) == 0.0
    assert float(SkyModel(degree=0, initial_color=(0.7, 0.5, 0.3)).dirichlet_energy().detach()) == 0.0
    sky = _random_sky()
    energy = float(sky.dirichlet_energy().detach())
    assert energy > 0
    c = sky.coefficients.detach()  # rows: band 1 (3), band 2 (5), band 3 (7)
    expected = 2 * c[0:3].square().sum() + 6 * c[3:8].square().sum() + 12 * c[8:15].square().sum()
    assert energy == pytest.approx(float(expected), rel=1e-12)
    # the constant (the mean colour) costs nothing; a higher band costs more for the same norm
    with torch.no_grad():
        sky.base.add_(3.0)
    assert float(sky.dirichlet_energy().detach()) == pytest.approx(energy, rel=1e-12)
    one, three = SkyModel(degree=3), SkyModel(degree=3)
    with torch.no_grad():
        one.coefficients[1, 0], three.coefficients[11, 0] = 1.0, 1.0
    assert float(one.dirichlet_energy().detach()) == pytest.approx(2.0)
    assert float(three.dirichlet_energy().detach()) == pytest.approx(12.0)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_the_dirichlet_energy_is_the_integral_of_the_squared_surface_gradient(degree):
    """The closed form against a quadrature of finite-difference gradients: the basis is orthonormal."""
    sky = _random_sky(degree, seed=degree)
    directions = _fibonacci_sphere(20_000)
    quadrature = float(_surface_gradient_sq(sky, directions).mean() * 4.0 * np.pi)
    assert float(sky.dirichlet_energy().detach()) == pytest.approx(quadrature, rel=1e-3)


def test_the_dirichlet_energy_gradient_matches_autograd_and_finite_differences():
    sky = _random_sky()
    energy = sky.dirichlet_energy()
    energy.backward()
    eigenvalues = torch.tensor([2.0] * 3 + [6.0] * 5 + [12.0] * 7, dtype=torch.float64)[:, None]
    torch.testing.assert_close(sky.coefficients.grad, 2.0 * eigenvalues * sky.coefficients.detach())
    assert sky.base.grad is None or float(sky.base.grad.abs().max()) == 0.0
    # and by finite differences, through the module as the optimiser sees it
    energy_of = _EnergyOf(sky)
    assert torch.autograd.gradcheck(lambda bands: torch.func.functional_call(energy_of, {"sky.coefficients": bands}, ()),
                                    (sky.coefficients.detach().clone().requires_grad_(True),))


class _EnergyOf(torch.nn.Module):
    """The energy as a module's output, so functional_call can swap the sky's coefficients."""

    def __init__(self, sky: SkyModel):
        super().__init__()
        self.sky = sky

    def forward(self) -> torch.Tensor:
        return self.sky.dirichlet_energy()


def test_the_smoothness_term_trains_only_when_its_weight_is_set(fast_config, tmp_path):
    from esgs.core.train.trainer import Trainer

    def run(weight: float) -> tuple[set, list, float]:
        trainer = Trainer(fast_config(out=tmp_path / f"smooth{weight}", iterations=6, densify=False,
                                      sky_smooth_weight=weight))
        trainer.setup()
        names = {term.name for term in trainer.loss_terms}
        values = [trainer.train_step(step).loss_values for step in range(1, 7)]
        return names, values, float(trainer.sky.dirichlet_energy().detach())

    names, values, smoothed = run(10.0)
    assert "sky_smooth" in names and all("sky_smooth" in step for step in values)
    assert values[0]["sky_smooth"] == 0.0  # the sky starts uniform
    names, values, free = run(0.0)
    assert "sky_smooth" not in names and not any("sky_smooth" in step for step in values)
    assert smoothed < 0.5 * free, (smoothed, free)
    # no sky model, no term
    trainer = Trainer(fast_config(out=tmp_path / "nosky", sky="none", sky_smooth_weight=1.0))
    trainer.setup()
    assert "sky_smooth" not in {term.name for term in trainer.loss_terms}


def test_the_smoothness_weight_round_trips_and_older_runs_read_it_as_off(fast_config, tmp_path):
    import argparse

    from esgs.core.commands import train as train_command
    from esgs.core.config import config_to_dict
    from esgs.core.errors import ConfigError
    from esgs.core.train.config import run_config_from_dict

    config = fast_config(sky_smooth_weight=0.25)
    data = json.loads(json.dumps(config_to_dict(config)))  # as config.json and checkpoints hold it
    assert data["sky_smooth_weight"] == 0.25 and run_config_from_dict(data).sky_smooth_weight == 0.25
    del data["sky_smooth_weight"]  # a run saved before the setting existed
    assert run_config_from_dict(data).sky_smooth_weight == 0.0
    with pytest.raises(ConfigError, match="sky_smooth_weight"):
        fast_config(sky_smooth_weight=-1.0).validate()
    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    assert train_command.build_config(parser.parse_args(["scene", "--out", str(tmp_path),
                                                         "--sky-smooth-weight", "0.5"])).sky_smooth_weight == 0.5
    with pytest.raises(ConfigError, match="--sky-smooth-weight"):
        train_command.build_config(parser.parse_args(["scene", "--out", str(tmp_path), "--vanilla",
                                                      "--sky-smooth-weight", "0.5"]))


def test_a_resumed_run_with_the_smoothness_prior_continues_exactly(fast_config, tmp_path):
    from esgs.core.train import train

    def config(out, **values):
        return fast_config(out=out, iterations=8, checkpoint_every=4, densify=False, sky_smooth_weight=1.0, **values)

    train(config(tmp_path / "full"))
    train_then_checkpoint(config(tmp_path / "split"), 4)
    train(config(tmp_path / "split", resume=True))
    a, b = load_sky(tmp_path / "full" / "sky.json"), load_sky(tmp_path / "split" / "sky.json")
    assert torch.equal(a.base, b.base) and torch.equal(a.coefficients, b.coefficients)


# --- the unseen-sky prior -------------------------------------------------------------------
def test_fibonacci_directions_are_unit_and_cover_the_sphere_evenly():
    from esgs.core.train.sky import fibonacci_sphere

    points = fibonacci_sphere(4000).double()
    assert torch.allclose(points.norm(dim=-1), torch.ones(4000, dtype=torch.float64), atol=1e-6)
    assert abs(float(points.mean(dim=0).norm())) < 1e-3  # no side favoured
    # every hemisphere of a few axes holds half the points
    for axis in torch.eye(3, dtype=torch.float64):
        assert abs(float((points @ axis > 0).double().mean()) - 0.5) < 0.01


def test_unseen_directions_are_those_no_ray_came_near_and_their_targets_are_sky_seen():
    from esgs.core.train.sky import UnseenSkyPrior, fibonacci_sphere

    rays = fibonacci_sphere(20_000)
    all_rays = rays[rays[:, 2] > -0.2]          # the views looked everywhere but far below the horizon
    sky_rays = all_rays[all_rays[:, 0] > 0.0]   # and saw sky only on the +x side
    prior = UnseenSkyPrior.from_rays(all_rays, sky_rays, samples=1000, radius_deg=3.0, neighbours=4)
    assert prior is not None
    assert bool((prior.unseen[:, 2] < -0.15).all())          # unseen: only the far-below cap
    assert 0.2 < prior.unseen_fraction < 0.45                # about (1 - 0.2) / 2 of the sphere
    assert bool((prior.seen[:, 0] > -0.06).all())           # targets among sky-seen directions only
    # a target is among the nearest sky-seen directions (cosines in descending order)
    cosines = prior.unseen @ prior.seen.T
    best = cosines.max(dim=1).values
    assert torch.allclose(cosines.gather(1, prior.neighbours[:, :1])[:, 0], best)
    # full coverage, or no sky seen: no prior
    assert UnseenSkyPrior.from_rays(rays, rays, samples=500, radius_deg=3.0) is None
    assert UnseenSkyPrior.from_rays(all_rays, all_rays[:0], samples=500) is None


def test_the_unseen_prior_costs_nothing_for_a_uniform_sky_and_pulls_unseen_directions_to_their_neighbours():
    from esgs.core.train.sky import UnseenSkyPrior, fibonacci_sphere

    rays = fibonacci_sphere(20_000)
    seen = rays[rays[:, 2] > 0.3]
    prior = UnseenSkyPrior.from_rays(seen, seen, samples=800, radius_deg=4.0)
    uniform = SkyModel(3, initial_color=(0.6, 0.4, 0.3))
    assert float(prior.loss(uniform).detach()) == pytest.approx(0.0, abs=1e-12)
    sky = SkyModel(3, initial_color=(0.6, 0.4, 0.3))
    with torch.no_grad():
        sky.coefficients.copy_(torch.randn(sky.coefficients.shape, generator=torch.Generator().manual_seed(3)))
    # the value by hand: logits at the unseen points against the mean logits of their neighbours
    with torch.no_grad():
        expected = (sky.logits(prior.unseen) - sky.logits(prior.seen)[prior.neighbours].mean(1)).square().mean()
    loss = prior.loss(sky)
    assert float(loss.detach()) == pytest.approx(float(expected), rel=1e-6)
    # descending it moves the unseen side towards the seen one, while the seen directions,
    # held by a data term, keep their colours
    target = sky.logits(seen).detach()
    optimizer = torch.optim.Adam(sky.parameters(), lr=0.05)
    for _ in range(300):
        optimizer.zero_grad()
        (prior.loss(sky) + 10.0 * (sky.logits(seen) - target).square().mean()).backward()
        optimizer.step()
    assert float(prior.loss(sky).detach()) < 0.2 * float(expected)
    assert float((sky.logits(seen) - target).abs().mean().detach()) < 0.3


def test_the_unseen_term_trains_only_when_its_weight_is_set_and_round_trips(fast_config, sky_scene, tmp_path):
    from esgs.core.config import config_from_dict, config_to_dict
    from esgs.core.train import TrainConfig
    from esgs.core.train.trainer import Trainer

    config = _config(fast_config, sky_scene, tmp_path / "unseen", iterations=4, sky_unseen_weight=0.5)
    trainer = Trainer(config)
    trainer.setup()
    assert "sky_unseen" in {term.name for term in trainer.loss_terms}
    assert 0.0 < trainer._unseen_sky.unseen_fraction < 1.0
    values = [trainer.train_step(step).loss_values for step in range(1, 5)]
    assert all("sky_unseen" in step for step in values)
    assert config_from_dict(TrainConfig, config_to_dict(config)).sky_unseen_weight == 0.5
    off = Trainer(_config(fast_config, sky_scene, tmp_path / "off", iterations=4))
    off.setup()
    assert "sky_unseen" not in {term.name for term in off.loss_terms}


@pytest.mark.parametrize("size", [(1920, 1080), (480, 270), (37, 23)])
def test_the_sky_image_from_a_coarse_grid_equals_every_pixels_sky(size):
    """The sky image interpolates logits evaluated on a grid ~0.6 degrees apart (at most every
    8th pixel; every pixel for wide pixels): within 1e-4 of evaluating every pixel for a strongly
    varying degree-3 sky (coefficients of std 1; learned skies: mean |c| 0.1-0.8, max ~2), exact
    on the grid's corner pixels, with gradients equal to every pixel's within 0.1 %."""
    width, height = size
    sky = SkyModel(degree=3)
    with torch.no_grad():
        sky.base.copy_(torch.tensor([0.4, -0.1, -0.6]))
        sky.coefficients.copy_(torch.randn(15, 3, generator=torch.Generator().manual_seed(3)))
    viewmat = torch.eye(4)
    viewmat[:3, :3] = torch.tensor([[0.0, 1.0, 0.0], [0.3, 0.0, -0.954], [-0.954, 0.0, -0.3]])
    viewmat[:3, :3] = torch.linalg.qr(viewmat[:3, :3])[0]
    K = torch.tensor([[0.8 * width, 0.0, width / 2], [0.0, 0.8 * width, height / 2], [0.0, 0.0, 1.0]])
    exact = sky.image(viewmat, K, width, height, stride=1)
    coarse = sky.image(viewmat, K, width, height)
    assert image_stride(K) == {1920: 8, 480: 3, 37: 1}[width]
    assert coarse.shape == exact.shape == (height, width, 3)
    assert float((coarse - exact).abs().max()) < 1e-4
    if width > 16:
        torch.testing.assert_close(coarse[0, 0], exact[0, 0], atol=1e-6, rtol=0)
        torch.testing.assert_close(coarse[-1, -1], exact[-1, -1], atol=1e-6, rtol=0)
    weights = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(4))
    coarse_grad = torch.autograd.grad((coarse * weights).sum(), sky.coefficients)[0]
    exact_grad = torch.autograd.grad((sky.image(viewmat, K, width, height, stride=1) * weights).sum(),
                                     sky.coefficients)[0]
    torch.testing.assert_close(coarse_grad, exact_grad, rtol=1e-3, atol=1e-3 * float(exact_grad.abs().max()))


# --- the direction grid (sky_grid_rows) ------------------------------------------------------
def _direction(azimuth_deg: float, elevation_deg: float) -> torch.Tensor:
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    return torch.tensor([[np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]], dtype=torch.float32)


def test_a_zero_grid_adds_nothing_and_a_cell_reads_its_value_at_its_centre_and_nothing_far_away():
    plain = SkyModel(3, initial_color=(0.6, 0.4, 0.3))
    gridded = SkyModel(3, initial_color=(0.6, 0.4, 0.3), grid_rows=10)  # 20 deg apart, 20 columns
    with torch.no_grad():
        plain.coefficients.copy_(torch.randn(plain.coefficients.shape, generator=torch.Generator().manual_seed(1)))
        gridded.coefficients.copy_(plain.coefficients)
    directions = torch.nn.functional.normalize(torch.randn(500, 3, generator=torch.Generator().manual_seed(2)), dim=1)
    torch.testing.assert_close(gridded.logits(directions), plain.logits(directions))
    # row r sits at elevation -90 + r * 180 / 9; column c at azimuth -180 + c * 360 / 20
    with torch.no_grad():
        gridded.grid[6, 3] = torch.tensor([1.0, -2.0, 0.5])
    at_centre = gridded.grid_logits(_direction(-180 + 3 * 18, -90 + 6 * 20))
    torch.testing.assert_close(at_centre, torch.tensor([[1.0, -2.0, 0.5]]))
    halfway = gridded.grid_logits(_direction(-180 + 3.5 * 18, -90 + 6 * 20))  # bilinear: half of it
    torch.testing.assert_close(halfway, torch.tensor([[0.5, -1.0, 0.25]]))
    assert float(gridded.grid_logits(_direction(90.0, -60.0)).abs().max()) == 0.0  # local support
    # the map wraps in azimuth: the last column blends into the first across +-180 degrees
    with torch.no_grad():
        gridded.grid.zero_()
        gridded.grid[4, 0] = 1.0
    elevation = -90 + 4 * 20
    torch.testing.assert_close(gridded.grid_logits(_direction(-180.0, elevation)),
                               gridded.grid_logits(_direction(180.0, elevation)))
    torch.testing.assert_close(gridded.grid_logits(_direction(180.0 - 9.0, elevation)), torch.full((1, 3), 0.5))


def test_the_grid_gradient_matches_finite_differences_and_the_file_round_trips(tmp_path):
    sky = SkyModel(2, initial_color=(0.5, 0.5, 0.5), grid_rows=6).double()
    with torch.no_grad():
        sky.grid.copy_(torch.randn(sky.grid.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64))
    directions = torch.nn.functional.normalize(torch.randn(40, 3, generator=torch.Generator().manual_seed(5),
                                                           dtype=torch.float64), dim=1)
    assert torch.autograd.gradcheck(lambda grid: torch.nn.functional.grid_sample(
        torch.cat([grid, grid[:, :1]], dim=1).permute(2, 0, 1)[None],
        torch.stack([torch.atan2(directions[:, 1], directions[:, 0]) / np.pi,
                     torch.asin(directions[:, 2]) / (np.pi / 2)], -1).view(1, -1, 1, 2),
        align_corners=True), (sky.grid.detach().clone().requires_grad_(),))
    # the model's own gradient equals that of the same reading written out
    sky.logits(directions).sum().backward()
    assert sky.grid.grad is not None and float(sky.grid.grad.abs().sum()) > 0
    sky = sky.float()
    path = save_sky(tmp_path / "sky.json", sky)
    back = load_sky(path)
    assert back.grid_rows == 6
    torch.testing.assert_close(back.grid, sky.grid)
    torch.testing.assert_close(back(directions.float()), sky(directions.float()))
    data = json.loads(path.read_text())
    data["grid"] = data["grid"][:-1]
    path.write_text(json.dumps(data))
    with pytest.raises(CheckpointError, match="grid"):
        load_sky(path)
    # a file written before the grid existed has none
    plain = SkyModel(3).to_dict()
    assert "grid" not in plain and SkyModel.from_dict(plain).grid is None


def test_with_a_grid_the_unseen_prior_moves_only_the_grid():
    from esgs.core.train.sky import UnseenSkyPrior, fibonacci_sphere

    rays = fibonacci_sphere(20_000)
    seen = rays[rays[:, 2] > 0.3]
    prior = UnseenSkyPrior.from_rays(seen, seen, samples=800, radius_deg=4.0)
    sky = SkyModel(3, initial_color=(0.6, 0.4, 0.3), grid_rows=12)
    with torch.no_grad():
        sky.coefficients.copy_(torch.randn(sky.coefficients.shape, generator=torch.Generator().manual_seed(3)))
    prior.loss(sky).backward()
    assert sky.coefficients.grad is None and sky.base.grad is None  # the harmonics are left alone
    moved = sky.grid.grad.abs().sum(dim=(1, 2))  # per row: only rows near unseen directions move
    assert float(moved[-1]) == 0.0 and float(moved[0]) > 0.0  # +z pole seen, -z pole not
    # descending it with the seen directions held by a data term (in a run: the photometric
    # loss) fills the unseen side in and leaves the seen colours as they were
    target = sky.logits(seen).detach()
    optimizer = torch.optim.Adam([sky.grid], lr=0.05)
    before = float(prior.loss(sky).detach())
    for _ in range(300):
        optimizer.zero_grad()
        (prior.loss(sky) + 10.0 * (sky.logits(seen) - target).square().mean()).backward()
        optimizer.step()
    assert float(prior.loss(sky).detach()) < 0.2 * before
    assert float((sky.logits(seen) - target).abs().mean().detach()) < 0.3


def test_a_run_with_a_grid_sky_trains_it_and_saves_it(fast_config, sky_scene, tmp_path):
    from esgs.core.train import train

    train(_config(fast_config, sky_scene, tmp_path / "grid", iterations=4, sky_grid_rows=8))
    saved = load_sky(tmp_path / "grid" / "sky.json")
    assert saved.grid.shape == (8, 16, 3)
    assert float(saved.grid.abs().max()) > 0  # the photometric loss reached it


def test_the_sky_learning_rate_decays_to_its_share_by_the_last_step(fast_config, tmp_path):
    import argparse

    from esgs.core.commands import train as train_command
    from esgs.core.config import config_to_dict
    from esgs.core.errors import ConfigError
    from esgs.core.train.config import run_config_from_dict
    from esgs.core.train.trainer import Trainer

    trainer = Trainer(fast_config(out=tmp_path / "decay", iterations=100, sky_lr=0.04, sky_lr_decay=0.1))
    trainer.setup()
    rates = []
    for step in (0, 50, 100, 200):
        trainer.optimizer.update_learning_rates(step)
        rates.append(trainer.optimizer.learning_rate("sky"))
    assert rates == pytest.approx([0.04, 0.04 * 0.1 ** 0.5, 0.004, 0.004])
    trainer = Trainer(fast_config(out=tmp_path / "constant", iterations=100, sky_lr=0.04, sky_lr_decay=1.0))
    trainer.setup()
    trainer.optimizer.update_learning_rates(100)
    assert trainer.optimizer.learning_rate("sky") == pytest.approx(0.04)
    for bad in (0.0, 1.5):
        with pytest.raises(ConfigError, match="sky_lr_decay"):
            fast_config(sky_lr_decay=bad).validate()
    parser = argparse.ArgumentParser()
    train_command.add_arguments(parser)
    args = ["scene", "--out", str(tmp_path), "--sky-lr-decay", "0.5"]
    assert train_command.build_config(parser.parse_args(args)).sky_lr_decay == 0.5
    for flag in (["--sky-lr-decay", "0.5"], ["--sky-grid-rows", "8"], ["--sky-init", "black"]):  # --vanilla has no sky model to set
        with pytest.raises(ConfigError, match=flag[0]):
            train_command.build_config(parser.parse_args(["scene", "--out", str(tmp_path), "--vanilla", *flag]))
    # runs saved before the decay trained the sky at a constant rate
    data = json.loads(json.dumps(config_to_dict(fast_config())))
    del data["sky_lr_decay"]
    assert run_config_from_dict(data).sky_lr_decay == 1.0


def test_without_sky_marks_the_sky_starts_from_the_images_mean_colour_or_black(fast_config, tiny_scene, tmp_path):
    import torch

    from esgs.core.train.trainer import Trainer

    trainer = Trainer(fast_config(out=tmp_path / "images", mask_source="none"))
    trainer.setup()
    pixels = torch.cat([view.image.reshape(-1, 3).double() / 255.0 for view in trainer.data.train])
    mean = pixels.mean(dim=0).clamp(0.01, 0.99)
    directions = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    colours = torch.sigmoid(trainer.sky.logits(directions)).double()
    torch.testing.assert_close(colours, mean.expand_as(colours).to(colours), atol=1e-5, rtol=0)
    black = Trainer(fast_config(out=tmp_path / "black", mask_source="none", sky_init="black"))
    black.setup()
    assert float(torch.sigmoid(black.sky.logits(directions)).max()) < 0.05  # 3DGS's black background


def test_runs_saved_before_sky_init_read_as_black():
    from esgs.core.train.config import with_predating_values

    assert with_predating_values({"scene": "s", "out": "o"})["sky_init"] == "black"


def test_a_run_without_the_sky_model_is_not_stale_for_the_sky_models_settings(tmp_path):
    from esgs.core.config import config_to_dict
    from esgs.core.experiments.runs import effective_settings
    from esgs.core.train.config import SKY_MODEL_SETTINGS, TrainConfig, with_predating_values

    vanilla = json.loads(json.dumps(config_to_dict(TrainConfig(scene=tmp_path, out=tmp_path, sky="none"))))
    saved = dict(vanilla)
    del saved["sky_init"]  # saved before the setting existed: reads as black
    saved = with_predating_values(saved)
    assert saved["sky_init"] != vanilla["sky_init"]
    assert effective_settings(saved) == effective_settings(vanilla)
    # with the sky model the start counts
    envmap = {**vanilla, "sky": "envmap"}
    assert effective_settings({**envmap, "sky_init": "black"}) != effective_settings(envmap)
    assert "sky_init" in SKY_MODEL_SETTINGS
