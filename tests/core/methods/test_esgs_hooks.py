"""ESGS hooks in real (tiny) training runs: prior losses act, masks hold, GPDFN trains and bakes."""
from __future__ import annotations


import numpy as np
import pytest
import torch

from esgs.core.colmap import read_model
from esgs.core.errors import ConfigError
from esgs.core.methods import ESGSConfig
from esgs.core.methods.esgs.gpdfn_hook import GPDFNHook
from esgs.core.methods.esgs.hooks import esgs_hooks
from esgs.core.priors import write_prior_maps
from esgs.core.render import rasterization
from esgs.core.render.surface import median_surface_depth, median_surface_normals
from esgs.core.train.config import TrainConfig
from esgs.core.train.hooks import TrainHook
from esgs.core.methods import make_trainer
from tests.core.train.scene import ground_truth_gaussians, make_scene


def _write_gt_priors(scene, sky_rows: int = 0):
    """Render the known Gaussians' depth and camera-frame normals for every view as gt priors."""
    truth = ground_truth_gaussians(14, 0)
    model = read_model(scene / "sparse" / "0")
    for image in model.images.values():
        camera = model.cameras[image.camera_id]
        viewmat = torch.tensor(image.world_to_camera(), dtype=torch.float32)[None]
        K = torch.tensor(camera.K(), dtype=torch.float32)[None]
        render, alpha, meta = rasterization(truth["means"], truth["quats"], truth["scales"], truth["opacities"],
                                            truth["colors"], viewmat, K, camera.width, camera.height,
                                            render_depth=True, render_normals=True, backend="reference")
        channels = meta["channels"]
        depth = render[0, :, :, channels["depth"]][..., 0].numpy()
        normal = render[0, :, :, channels["normal"]].numpy()
        normal = normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-6)
        mask = alpha[0, :, :, 0].numpy() > 0.5
        if sky_rows:
            depth[:sky_rows] = 1000.0  # a corrupt "sky" prior: must be masked out
            mask[:sky_rows] = False
        write_prior_maps(scene, "gt", image.name, depth=depth * mask + depth * (~mask) * (sky_rows > 0),
                         normal=normal, mask=mask)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = make_scene(tmp_path_factory.mktemp("esgs") / "scene", views=6, width=32, height=24)
    _write_gt_priors(root, sky_rows=4)
    return root


def _trainer(scene, out, esgs: ESGSConfig, iterations=40, progress=None, **overrides):
    config = TrainConfig(scene=scene, out=out, iterations=iterations, backend="cpu", evaluate=False, densify_until=0,
                         checkpoint_every=0, progress_every=1000, test_every=0, lpips=False, sh_degree=1,
                         mask_source="none", method="esgs", method_config=esgs, **overrides)
    trainer = make_trainer(config, progress=progress)
    trainer.setup()
    return trainer


class _Recorder(TrainHook):
    name = "recorder"

    def __init__(self):
        self.values = []

    def after_backward(self, trainer, context):
        self.values.append(dict(context.loss_values))


def test_config_errors_are_clear():
    with pytest.raises(ConfigError, match="need a prior source"):
        ESGSConfig(depth=True).validate()
    with pytest.raises(ConfigError, match="fused_k"):
        ESGSConfig(gpdfn=True, fused_k=0).validate()
    assert esgs_hooks(ESGSConfig()) == []


def _depth_error(trainer, priors, depth_render: str = "expected") -> float:
    """Mean |log rendered depth - log prior depth| over the valid prior pixels of every training
    view; ``depth_render`` "plane": the depth of each pixel's median surface instead."""
    errors = []
    with torch.no_grad():
        params = trainer.gaussians.render_params(1)
        for view in trainer.data.train:
            output = trainer.render(params, view, render_depth=True)
            if depth_render == "expected":
                depth, covered = output.depth[..., 0], output.alpha[..., 0] > 0.5
            else:
                depth, covered = median_surface_depth(output.meta["median_ids"][0], params.means, params.quats,
                                                      params.scales, view.viewmat, view.K, kind=depth_render)
            prior = priors[view.name]
            valid = prior.mask & (depth > 0) & covered
            errors.append((depth[valid].log() - prior.depth[valid].log()).abs().mean())
    return float(torch.stack(errors).mean())


def test_prior_terms_are_added_and_pull_depth_onto_the_prior(scene, tmp_path):
    esgs = ESGSConfig(priors="gt", depth=True, normal=True, prior_start_step=0, depth_weight=1.0)
    trainer = _trainer(scene, tmp_path / "run", esgs)
    baseline = _trainer(scene, tmp_path / "base", ESGSConfig())
    recorder = _Recorder()
    trainer.hooks.append(recorder)
    assert {"depth_prior", "normal_prior"} <= {term.name for term in trainer.loss_terms}
    assert not {"depth_prior", "normal_prior"} & {term.name for term in baseline.loss_terms}
    priors = trainer.hooks[0].priors
    start_error = _depth_error(trainer, priors)
    for step in range(1, 41):
        trainer.train_step(step)
        baseline.train_step(step)
    assert all("normal_prior" in v and "depth_prior" in v for v in recorder.values)
    with_prior, without_prior = _depth_error(trainer, priors), _depth_error(baseline, priors)
    assert with_prior < 0.8 * start_error, (start_error, with_prior)
    assert with_prior < 0.9 * without_prior, (with_prior, without_prior)


def test_a_median_surface_depth_prior_pulls_that_surface_onto_the_prior(scene, tmp_path):
    esgs = ESGSConfig(priors="gt", depth=True, prior_start_step=0, depth_weight=1.0, depth_render="plane")
    trainer = _trainer(scene, tmp_path / "run", esgs)
    baseline = _trainer(scene, tmp_path / "base", ESGSConfig())
    priors = trainer.hooks[0].priors
    start_error = _depth_error(trainer, priors, "plane")
    for step in range(1, 41):
        trainer.train_step(step)
        baseline.train_step(step)
    with_prior, without_prior = _depth_error(trainer, priors, "plane"), _depth_error(baseline, priors, "plane")
    assert with_prior < 0.8 * start_error, (start_error, with_prior)
    assert with_prior < 0.9 * without_prior, (with_prior, without_prior)
    with pytest.raises(ConfigError, match="depth_render"):
        ESGSConfig(priors="gt", depth=True, depth_render="median").validate()


def test_a_median_surface_depth_is_refused_where_the_rasterizer_has_no_median_ids(scene, tmp_path):
    from types import SimpleNamespace

    from esgs.core.methods.esgs.prior_hook import PriorLossHook

    esgs = ESGSConfig(priors="gt", depth=True, prior_start_step=0, depth_render="plane")
    # a run on the cuda backend: refused at setup, before any prior is loaded
    cuda_run = SimpleNamespace(device=torch.device("cuda"), backend="cuda", scaled_step=lambda step, minimum=0: step)
    with pytest.raises(ConfigError, match="cpu and reference"):
        PriorLossHook(esgs).setup(cuda_run)
    # a render without the ids (what gsplat returns): the loss term says why
    trainer = _trainer(scene, tmp_path / "run", esgs)
    hook = trainer.hooks[0]
    view = trainer.data.train[0]
    params = trainer.gaussians.render_params(1)
    output = trainer.render(params, view, render_depth=True)
    output.meta.pop("median_ids")
    context = SimpleNamespace(view=view, output=output, params=params, depth=output.depth, alpha=output.alpha,
                              image=output.image, target=None)
    with pytest.raises(ConfigError, match="no median"):
        hook._depth_term(context)


def _median_normal_error(trainer, priors) -> float:
    """Mean angle (radians) between each pixel's median-surface normal and the prior normal over
    the valid prior pixels of every training view."""
    angles = []
    with torch.no_grad():
        params = trainer.gaussians.render_params(1)
        for view in trainer.data.train:
            output = trainer.render(params, view)
            normals, surface = median_surface_normals(output.meta["median_ids"][0], params.means, params.quats,
                                                      params.scales, view.viewmat)
            prior = priors[view.name]
            valid = prior.mask & surface & (prior.normal.norm(dim=-1) > 0.5)
            cos = (normals[valid] * prior.normal[valid]).sum(-1).clamp(-1, 1)
            angles.append(torch.arccos(cos).mean())
    return float(torch.stack(angles).mean())


@pytest.mark.parametrize("normal_render", ["median", "thin"])
def test_a_median_surface_normal_prior_turns_the_surface_onto_the_prior(scene, tmp_path, normal_render):
    esgs = ESGSConfig(priors="gt", normal=True, prior_start_step=0, normal_weight=0.5, normal_render=normal_render)
    # the Gaussians start round, their "shortest" axis 90 degrees off the plane's normal, and the
    # prior can only turn them: a rotation lr that lets 40 steps swing an axis that far
    trainer = _trainer(scene, tmp_path / "run", esgs, rotation_lr=0.05)
    baseline = _trainer(scene, tmp_path / "base", ESGSConfig(), rotation_lr=0.05)
    term = next(term for term in trainer.loss_terms if term.name == "normal_prior")
    assert term.needs == frozenset()  # read from the Gaussians: no normal channel is rendered
    priors = trainer.hooks[0].priors
    start_error = _median_normal_error(trainer, priors)
    for step in range(1, 41):
        trainer.train_step(step)
        baseline.train_step(step)
    with_prior, without_prior = _median_normal_error(trainer, priors), _median_normal_error(baseline, priors)
    assert with_prior < 0.4 * start_error, (start_error, with_prior)
    assert with_prior < 0.5 * without_prior, (with_prior, without_prior)
    with pytest.raises(ConfigError, match="normal_render"):
        ESGSConfig(priors="gt", normal=True, normal_render="plane").validate()


@pytest.mark.parametrize("normal_render", ["median", "thin"])
def test_a_median_surface_normal_prior_never_moves_or_fades_a_gaussian(scene, tmp_path, normal_render):
    """The composited normal's loss reaches positions and opacities through the blend; the
    median surface's normal and thinness reach only rotations (and, for thin, scales)."""
    from types import SimpleNamespace

    grads = {}
    for mode in ("composited", normal_render):
        esgs = ESGSConfig(priors="gt", normal=True, prior_start_step=0, normal_render=mode)
        trainer = _trainer(scene, tmp_path / mode, esgs)
        with torch.no_grad():  # Gaussians start round, and a ball's thinness does not change as it turns
            scales = trainer.gaussians.params["log_scales"]
            scales += 0.5 * torch.randn(scales.shape, generator=torch.Generator().manual_seed(0))
        view = trainer.data.train[1]
        params = trainer.gaussians.render_params(1)
        output = trainer.render(params, view, render_normals=True)
        context = SimpleNamespace(view=view, output=output, params=params, normals=output.normals,
                                  alpha=output.alpha, image=output.image, target=output.image.detach())
        loss = trainer.hooks[0]._normal_term(context)
        raw = trainer.gaussians.params
        names = {"means": "means", "quats": "quats", "scales": "log_scales", "opacities": "opacity_logit"}
        values = torch.autograd.grad(loss, [raw[name] for name in names.values()], allow_unused=True)
        grads[mode] = {name: 0.0 if g is None else float(g.norm()) for name, g in zip(names, values)}
    assert grads["composited"]["means"] > 0 and grads["composited"]["opacities"] > 0
    assert grads[normal_render]["means"] == 0.0 and grads[normal_render]["opacities"] == 0.0
    assert grads[normal_render]["quats"] > 0
    assert (grads[normal_render]["scales"] > 0) == (normal_render == "thin")


def test_a_median_surface_normal_falls_back_where_the_rasterizer_has_no_median_ids(scene, tmp_path):
    from types import SimpleNamespace

    from esgs.core.methods.esgs.prior_hook import PriorLossHook

    esgs = ESGSConfig(priors="gt", normal=True, prior_start_step=0, normal_render="thin")
    # a run on the cuda backend keeps a normal prior, the composited one, and says so
    messages, terms = [], []
    cuda_run = SimpleNamespace(device=torch.device("cpu"), backend="cuda", scaled_step=lambda step, minimum=0: step,
                               train_views=[], scene=scene, message=messages.append, add_loss_term=terms.append,
                               extent=1.0)
    hook = PriorLossHook(esgs)
    hook._load = lambda run: None  # no views to load in this stand-in run
    hook.setup(cuda_run)
    assert hook.normal_render == "composited"
    assert any("normal_render 'thin' needs the median surface" in m and "composited" in m for m in messages)
    assert [term.needs for term in terms if term.name == "normal_prior"] == [frozenset({"normals"})]
    trainer = _trainer(scene, tmp_path / "run", esgs)
    view = trainer.data.train[0]
    params = trainer.gaussians.render_params(1)
    output = trainer.render(params, view)
    output.meta.pop("median_ids")
    context = SimpleNamespace(view=view, output=output, params=params, normals=None, alpha=output.alpha,
                              image=output.image, target=None)
    with pytest.raises(ConfigError, match="no median"):
        trainer.hooks[0]._normal_term(context)


def test_sky_pixels_never_reach_the_loss(scene, tmp_path):
    esgs = ESGSConfig(priors="gt", depth=True, prior_start_step=0)
    trainer = _trainer(scene, tmp_path / "run", esgs)
    hook = trainer.hooks[0]
    prior = hook.priors[trainer.data.train[0].name]
    assert not prior.mask[:4].any()  # the corrupt rows are masked
    unmasked = _trainer(scene, tmp_path / "run2", ESGSConfig(priors="gt", depth=True, prior_start_step=0,
                                                              use_masks=False))
    assert unmasked.hooks[0].priors[trainer.data.train[0].name].mask[:4].all()


def test_gpdfn_hook_trains_its_module_and_bakes_residuals(scene, tmp_path):
    esgs = ESGSConfig(gpdfn=True, fused_k=3, gpdfn_lr=5e-3)
    trainer = _trainer(scene, tmp_path / "run", esgs, iterations=60)
    hook = next(h for h in trainer.hooks if isinstance(h, GPDFNHook))
    assert "gpdfn" in trainer.optimizer.groups and not trainer.optimizer.groups["gpdfn"].per_gaussian
    before = [p.detach().clone() for p in hook.module.parameters()]
    for step in range(1, 61):
        trainer.train_step(step)
    changed = [not torch.equal(a, b.detach()) for a, b in zip(before, hook.module.parameters())]
    assert all(changed), "every GPDFN weight (offsets included) must learn"
    params = trainer.gaussians.render_params(1)
    fused = hook.model_params(trainer, params)  # every Gaussian fused (a step fuses what its view can draw)
    assert not torch.allclose(fused.opacities, params.opacities)
    hook.bake(trainer.gaussians)
    baked = trainer.gaussians.render_params(1)
    torch.testing.assert_close(baked.opacities, fused.opacities, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(baked.scales, fused.scales, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(baked.colors.dc, fused.colors.dc, rtol=1e-5, atol=1e-6)


def test_cli_runs_full_esgs_and_saves_its_settings(scene, tmp_path):
    import json
    import subprocess
    import sys

    from esgs.core.formats.ply import read_gaussians_ply

    out = tmp_path / "run"
    command = [sys.executable, "-m", "esgs.core", "train", str(scene), "--out", str(out), "--iterations", "12",
               "--backend", "cpu", "--test-every", "3", "--no-lpips", "--quiet", "--sh-degree", "1",
               "--priors", "gt", "--depth", "--normal", "--gpdfn", "--fused-k", "2", "--prior-start-step", "0"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    saved = json.loads((out / "config.json").read_text())["method_config"]
    assert saved["depth"] and saved["normal"] and saved["gpdfn"] and saved["fused_k"] == 2 and saved["priors"] == "gt"
    assert len(read_gaussians_ply(out / "point_cloud.ply").means) > 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["psnr"] > 5
    bad = subprocess.run([sys.executable, "-m", "esgs.core", "train", str(scene), "--out", str(tmp_path / "r2"),
                          "--depth"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "need a prior source" in bad.stderr


def _add_observations(scene):
    """Give the tiny scene's images the keypoints of the points they see (tracks, as SfM would)."""
    from esgs.core.colmap import write_model

    model = read_model(scene / "sparse" / "0")
    tracks = {point_id: [] for point_id in model.points}
    ids = np.array(sorted(model.points))
    xyz = np.stack([model.points[i].xyz for i in ids])
    for image in model.images.values():
        camera = model.cameras[image.camera_id]
        local = xyz @ image.rotation_matrix().T + image.translation
        pixels = local[:, :2] / local[:, 2:] * np.diag(camera.K())[:2] + camera.K()[:2, 2]
        inside = (local[:, 2] > 0) & np.all((pixels >= 0) & (pixels < [camera.width, camera.height]), axis=1)
        image.points2d, image.point3d_ids = pixels[inside], ids[inside].astype(np.int64)
        for index, point_id in enumerate(ids[inside]):
            tracks[int(point_id)].append((image.image_id, index))
    for point_id, track in tracks.items():
        model.points[point_id].track_image_ids = np.array([t[0] for t in track], np.int64)
        model.points[point_id].track_point2d_idxs = np.array([t[1] for t in track], np.int64)
    write_model(model, scene / "sparse" / "0", overwrite=True)


def test_relative_priors_are_pinned_to_the_sfm_points(tmp_path):
    """NDN-like relative priors become metric (the scene's depth) with sfm alignment; render keeps them relative."""
    from esgs.core.priors import load_prior_maps

    root = make_scene(tmp_path / "scene", views=6, width=32, height=24)
    _write_gt_priors(root)
    _add_observations(root)
    for name in sorted(p.name for p in (root / "images").iterdir()):
        gt = load_prior_maps(root, "gt", name)
        relative = np.where(gt.mask, (gt.depth - 1.0) / 4.0, 0.0).astype(np.float32)
        write_prior_maps(root, "rel", name, depth=relative, mask=gt.mask, relative_depth=True)
    messages = []
    config = dict(priors="rel", depth=True, prior_start_step=0)
    pinned = _trainer(root, tmp_path / "a", ESGSConfig(**config), progress=lambda event: messages.append(event.message))
    shaped = _trainer(root, tmp_path / "b", ESGSConfig(relative_alignment="render", **config))
    assert any("aligned to SfM points in 6/6 views" in str(m) for m in messages), messages
    for view in pinned.data.train:
        prior, gt = pinned.hooks[0].priors[view.name], load_prior_maps(root, "gt", view.name)
        assert not bool(prior.relative) and bool(shaped.hooks[0].priors[view.name].relative)
        valid = prior.mask.numpy() & (gt.depth > 0)
        error = np.abs(prior.depth.numpy()[valid] - gt.depth[valid]) / gt.depth[valid]
        assert np.median(error) < 0.03, np.median(error)  # the points are jittered centres, not the surface


def test_a_view_whose_pinned_prior_contradicts_its_sfm_points_trains_without_priors(tmp_path):
    """The confidence gate: a prediction off by more than max_alignment_error at the image's own
    SfM points is dropped whole (depth and normal); the other views keep theirs; 0 keeps every view."""
    from esgs.core.priors import load_prior_maps

    root = make_scene(tmp_path / "scene", views=6, width=32, height=24)
    _write_gt_priors(root)
    _add_observations(root)
    names = sorted(p.name for p in (root / "images").iterdir())
    failed = set(names[:3])
    rng = np.random.default_rng(0)
    for name in names:
        gt = load_prior_maps(root, "gt", name)
        relative = np.where(gt.mask, (gt.depth - 1.0) / 4.0, 0.0).astype(np.float32)
        if name in names[:2]:  # a failed prediction: the shape drowned in noise as large as the depth range
            relative = np.where(gt.mask, relative + rng.uniform(-0.3, 0.3, relative.shape), 0.0).astype(np.float32)
        if name == names[2]:  # a failed prediction the fit refuses: near and far swapped
            relative = np.where(gt.mask, 1.0 - relative, 0.0).astype(np.float32)
        write_prior_maps(root, "rel", name, depth=relative, normal=gt.normal, mask=gt.mask, relative_depth=True)
    messages = []
    config = dict(priors="rel", depth=True, normal=True, prior_start_step=0)
    # the tiny scene's depths span only 2-3 units, so a failed map still fits within ~10 %: the
    # gate is set lower than the default here; the good views fit to ~1 %
    gated = _trainer(root, tmp_path / "a", ESGSConfig(max_alignment_error=0.05, **config),
                     progress=lambda event: messages.append(event.message))
    kept = _trainer(root, tmp_path / "b", ESGSConfig(max_alignment_error=0.0, **config))
    assert any("3 view(s) train without priors" in str(m) and "inverted" in str(m) for m in messages), messages
    for view in gated.data.train:
        prior, everything = gated.hooks[0].priors[view.name], kept.hooks[0].priors[view.name]
        assert everything.depth is not None and everything.normal is not None
        # without the gate the inverted view falls back to the per-step fit (stays relative)
        assert bool(everything.relative) == (view.name == names[2])
        if view.name in failed:
            assert prior.depth is None and prior.normal is None
        else:
            assert prior.depth is not None and torch.equal(prior.normal, everything.normal)
    with pytest.raises(ConfigError, match="max_alignment_error"):
        ESGSConfig(max_alignment_error=-1.0, **config).validate()


def _sky_shortfall(trainer, priors) -> float:
    """Mean over training views of the sky loss: how much the Gaussians draw over sky pixels nearer than the far surface."""
    from esgs.core.priors.losses import sky_loss

    values = []
    with torch.no_grad():
        params = trainer.gaussians.render_params(1)
        for view in trainer.data.train:
            output = trainer.render(params, view, render_depth=True)
            prior = priors[view.name]
            values.append(sky_loss(output.depth[..., 0], output.alpha[..., 0], prior.sky, prior.far))
    return float(torch.stack(values).mean())


def test_the_sky_loss_pushes_what_covers_sky_pixels_beyond_the_far_surface(scene, tmp_path):
    """Sky pixels of a source whose mask marks no-surface pixels (mask_kind surface) get the sky
    term; a coverage-only source gets none; a run with it draws far less in front of the sky."""
    from esgs.core.priors import load_prior_maps

    for view in sorted(p.name for p in (scene / "images").iterdir()):
        gt = load_prior_maps(scene, "gt", view)
        write_prior_maps(scene, "surface", view, depth=np.where(gt.mask, gt.depth, 0.0), normal=gt.normal,
                         mask=gt.mask, mask_kind="surface")
    messages = []
    esgs = ESGSConfig(priors="surface", sky_weight=50.0, prior_start_step=0)
    # the loss moves Gaussians (it never touches opacity): a position lr that lets 40 steps show it
    fast = {"position_lr_init": 1e-2, "position_lr_final": 1e-2}
    trainer = _trainer(scene, tmp_path / "sky", esgs, progress=lambda event: messages.append(event.message), **fast)
    baseline = _trainer(scene, tmp_path / "base", ESGSConfig(), **fast)
    assert "sky" in {term.name for term in trainer.loss_terms}
    priors = trainer.hooks[0].priors
    for view in trainer.data.train:
        prior = priors[view.name]
        # the fixture's sky rows, and wherever the known Gaussians leave the view uncovered
        assert prior.sky[:4].all() and torch.equal(prior.sky, ~prior.mask)
        valid = prior.depth[prior.mask]
        assert float(prior.far) == pytest.approx(float(torch.quantile(valid, 0.99)), rel=1e-6)
    start = _sky_shortfall(trainer, priors)
    assert start > 0.003  # the scene's Gaussians do cover the rows called sky, at surface depth
    for step in range(1, 41):
        trainer.train_step(step)
        baseline.train_step(step)
    with_sky, without_sky = _sky_shortfall(trainer, priors), _sky_shortfall(baseline, priors)
    assert with_sky < 0.5 * without_sky, (start, with_sky, without_sky)
    # a coverage mask (this fixture's gt) says nothing about sky: no term, and the log says so
    coverage = _trainer(scene, tmp_path / "cov", ESGSConfig(priors="gt", depth=True, sky_weight=1.0),
                        progress=lambda event: messages.append(event.message))
    assert "sky" not in {term.name for term in coverage.loss_terms}
    assert any("sky loss is off" in str(m) for m in messages), messages
    # masks off: nothing is known to be sky either
    unmasked = _trainer(scene, tmp_path / "nomask", ESGSConfig(priors="surface", sky_weight=1.0, use_masks=False))
    assert "sky" not in {term.name for term in unmasked.loss_terms}
    with pytest.raises(ConfigError, match="sky_weight"):
        ESGSConfig(sky_weight=-1.0).validate()


def test_gpdfn_starts_from_the_run_seed_whatever_ran_before(scene, tmp_path):
    """Same seed, same initial fusion weights, even after other draws from torch's global stream."""
    def initial_weights(out, seed):
        trainer = _trainer(scene, out, ESGSConfig(gpdfn=True), seed=seed)
        hook = next(h for h in trainer.hooks if isinstance(h, GPDFNHook))
        return [p.detach().clone() for p in hook.module.parameters()], torch.get_rng_state()

    first, _ = initial_weights(tmp_path / "a", 5)
    torch.rand(1000)  # what another run in the same process would leave behind
    again, _ = initial_weights(tmp_path / "b", 5)
    other, _ = initial_weights(tmp_path / "c", 6)
    assert all(torch.equal(a, b) for a, b in zip(first, again))
    assert not all(torch.equal(a, b) for a, b in zip(first, other))


def test_a_confidence_map_scales_the_prior_losses_the_trainer_adds(scene, tmp_path):
    """The same maps with confidence 0.5 everywhere: both prior terms of the first step are half."""
    import shutil

    from esgs.core.formats.scene_dir import SceneDir
    from esgs.core.priors import load_prior_maps

    copy = tmp_path / "scene"
    shutil.copytree(scene, copy)
    model = read_model(copy / "sparse" / "0")
    for image in model.images.values():
        maps = load_prior_maps(copy, "gt", image.name)
        write_prior_maps(copy, "halfsure", image.name, depth=maps.depth, normal=maps.normal, mask=maps.mask,
                         confidence=np.full(maps.mask.shape, 0.5, np.float32))
    assert SceneDir(copy).confidence_map("halfsure", image.name).is_file()
    values = {}
    for source in ("gt", "halfsure"):
        esgs = ESGSConfig(priors=source, depth=True, normal=True, prior_start_step=0, sky_weight=0.0)
        trainer = _trainer(copy, tmp_path / source, esgs)
        confidence = trainer.hooks[0].priors[trainer.data.train[0].name].confidence
        assert confidence is None if source == "gt" else bool((confidence == 0.5).all())
        recorder = _Recorder()
        trainer.hooks.append(recorder)
        trainer.train_step(1)
        values[source] = recorder.values[0]
    for term in ("depth_prior", "normal_prior"):
        assert values["gt"][term] > 0
        assert values["halfsure"][term] == pytest.approx(0.5 * values["gt"][term], rel=1e-5)


def test_grazing_prior_pixels_weigh_less_in_the_depth_loss_only(scene, tmp_path):
    """depth_incidence: the depth loss's weights are the incidence weights of the view's prior
    normals (times its confidence); the normal loss keeps its own; the first step's depth term
    shrinks and the normal term does not change."""
    from esgs.core.priors.losses import incidence_weights

    values, hooks = {}, {}
    for name, incidence in (("plain", 0.0), ("grazing", 0.9)):
        esgs = ESGSConfig(priors="gt", depth=True, normal=True, prior_start_step=0, sky_weight=0.0,
                          depth_incidence=incidence)
        trainer = _trainer(scene, tmp_path / name, esgs)
        hooks[name] = trainer.hooks[0]
        recorder = _Recorder()
        trainer.hooks.append(recorder)
        trainer.train_step(1)
        values[name] = recorder.values[0]
    view = trainer.data.train[0]
    plain, grazing = hooks["plain"].priors[view.name], hooks["grazing"].priors[view.name]
    assert plain.depth_trust is None and grazing.confidence is None
    expected = incidence_weights(grazing.normal, view.K, 0.9)
    assert torch.allclose(grazing.depth_trust, expected)
    assert float(expected[grazing.mask].min()) < 0.9  # the scene's tilted surfaces weigh less
    assert values["grazing"]["depth_prior"] < 0.9 * values["plain"]["depth_prior"]
    assert values["grazing"]["normal_prior"] == pytest.approx(values["plain"]["normal_prior"], rel=1e-6)


def test_a_decaying_depth_weight_falls_geometrically_to_its_end_fraction(scene, tmp_path):
    esgs = ESGSConfig(priors="gt", depth=True, prior_start_step=3000, depth_decay=0.1, sky_weight=0.0)
    trainer = _trainer(scene, tmp_path / "decay", esgs, iterations=100)
    hook = trainer.hooks[0]
    first, last = trainer.scaled_step(3000), trainer.scaled_step(30_000)
    assert (first, last) == (10, 100)
    assert hook._depth_decay_factor(0) == 1.0 and hook._depth_decay_factor(first) == 1.0
    assert hook._depth_decay_factor((first + last) // 2) == pytest.approx(0.1 ** 0.5)
    assert hook._depth_decay_factor(last) == pytest.approx(0.1)
    constant = _trainer(scene, tmp_path / "constant", ESGSConfig(priors="gt", depth=True, sky_weight=0.0), iterations=100)
    assert constant.hooks[0]._depth_decay_factor(last) == 1.0


def test_prior_points_seed_gaussians_on_the_prior_surface_and_never_from_sky(scene, tmp_path):
    plain = _trainer(scene, tmp_path / "plain", ESGSConfig(priors="gt", depth=True))
    seeded = _trainer(scene, tmp_path / "seeded", ESGSConfig(priors="gt", depth=True, prior_points=25))
    sfm = len(plain.data.points_xyz)
    assert len(plain.gaussians) == sfm
    added = len(seeded.gaussians) - sfm
    assert 0 < added <= 25 * len(seeded.data.train)
    # the seeds follow the SfM points in the initial model (Morton order may shuffle rows:
    # compare as a set of positions far from every SfM point instead of by index)
    means = seeded.gaussians.params["means"].detach().double().numpy()
    sfm_points = plain.data.points_xyz
    nearest = np.min(np.linalg.norm(means[:, None, :] - sfm_points[None, :, :], axis=-1), axis=1)
    new = means[nearest > 1e-5]  # float32 storage rounds the SfM points by ~1e-7
    assert len(new) == added
    # on the ground plane of the scene (|z| <= a few of its 0.02 jitter), inside its extent: none
    # comes from the masked "sky" rows, whose corrupt prior depth is 1000
    assert np.abs(new[:, 2]).max() < 0.15
    assert np.abs(new[:, :2]).max() < 1.3
    # the same run seed draws the same pixels
    again = _trainer(scene, tmp_path / "again", ESGSConfig(priors="gt", depth=True, prior_points=25))
    np.testing.assert_array_equal(again.gaussians.params["means"].detach().numpy(),
                                  seeded.gaussians.params["means"].detach().numpy())


def test_seeding_alone_loads_the_priors_and_still_keeps_to_the_maps_mask(scene, tmp_path):
    with pytest.raises(ConfigError, match="prior_points"):
        ESGSConfig(prior_points=10).validate()
    alone = ESGSConfig(priors="gt", prior_points=25, sky_weight=0.0, use_masks=False)
    assert alone.enabled and not (alone.depth or alone.normal or alone.sky_loss_on)
    trainer = _trainer(scene, tmp_path / "alone", alone)
    added = len(trainer.gaussians) - len(trainer.data.points_xyz)
    assert 0 < added <= 25 * len(trainer.data.train)
    # masks off for the losses, but no seed from the sky rows (corrupt depth 1000, outside the map's mask)
    assert trainer.gaussians.params["means"].detach()[:, 2].abs().max() < 0.15
