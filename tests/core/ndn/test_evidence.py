"""Evidence conditioning and the sky head of the completion network (core/ndn/evidence.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from esgs.core.errors import ConfigError
from esgs.core.ndn.config import NDNConfig, NDNDiffusionConfig, NDNModelConfig
from esgs.core.ndn.evidence import (EVIDENCE_MODES, bin_sparse_depth, depth_from_state, draw_evidence,
                                    encode_evidence, evidence_reference, log_reference, simulate_stereo,
                                    target_state)
from esgs.core.ndn.infer import arrays_evidence, evaluate_arrays, sky_iou
from esgs.core.ndn.train import build_model, evidence_batch, training_tensors

LOG_RANGE = 2.5


def completion_config(prediction: str = "regression", evidence: bool = True, sky: bool = True) -> NDNConfig:
    return NDNConfig(model=NDNModelConfig(base_channels=8, levels=2, time_dim=16, working_size=32, evidence=evidence,
                                          sky=sky),
                     diffusion=NDNDiffusionConfig(timesteps=50, sample_steps=3, prediction=prediction,
                                                  depth_state="log"))


def _scene_batch(batch: int = 4, height: int = 16, width: int = 24, seed: int = 0):
    """Depth of a ground plane rising to a horizon, sky in the top rows, and sparse points on it."""
    generator = torch.Generator().manual_seed(seed)
    rows = torch.arange(height, dtype=torch.float32)[:, None].expand(height, width)
    depth = (60.0 / (rows - 3.0).clamp_min(0.5)).expand(batch, height, width).clone()
    mask = rows.expand(batch, height, width) >= 4  # rows 0-3: sky
    depth = torch.where(mask, depth, torch.zeros_like(depth))
    points = torch.rand((batch, height, width), generator=generator) < 0.1
    sfm = torch.where(points & mask, depth * 1.01, torch.zeros_like(depth))
    return depth, mask, sfm


def test_sparse_points_are_binned_to_the_median_depth_of_each_working_pixel():
    uv = np.array([[0.5, 0.5], [1.5, 0.5], [2.0, 1.0], [7.9, 3.9], [-1.0, 2.0], [3.0, 9.0]])
    depth = np.array([1.0, 3.0, 8.0, 5.0, 7.0, 7.0])
    binned = bin_sparse_depth(uv, depth, image_size=(8, 4), working_size=(2, 2))  # 4x2 image px per cell
    # cell (0, 0) holds the first three points (median 3), cell (1, 1) the fourth; two are outside
    np.testing.assert_allclose(binned, [[3.0, 0.0], [0.0, 5.0]])
    two = bin_sparse_depth(uv[:2], depth[:2], (8, 4), (2, 2))
    assert two[0, 0] == pytest.approx(2.0)  # an even count: the mean of the middle two
    assert not bin_sparse_depth(np.zeros((0, 2)), np.zeros(0), (8, 4), (2, 2)).any()


def test_the_state_about_the_evidence_reference_reads_back_as_metres():
    depth, mask, sfm = _scene_batch()
    reference = evidence_reference(sfm)
    for index in range(depth.shape[0]):
        assert float(reference[index]) == pytest.approx(float(sfm[index][sfm[index] > 0].median()))
    state = target_state(depth, mask, reference, LOG_RANGE)
    assert state.shape == (4, 1, 16, 24)
    assert torch.all(state[:, 0][~mask] == 1.0)  # no surface reads far
    metric = depth_from_state(state, reference, LOG_RANGE)[:, 0]
    inside = mask & (depth / reference.view(-1, 1, 1) < math.exp(LOG_RANGE) * 0.99)
    torch.testing.assert_close(metric[inside], depth[inside], rtol=1e-5, atol=0)
    encoded = encode_evidence(sfm, torch.zeros_like(sfm), reference, LOG_RANGE)
    assert encoded.shape == (4, 4, 16, 24)
    assert torch.equal(encoded[:, 1] > 0, sfm > 0) and not encoded[:, 2:].any()
    back = depth_from_state(encoded[:, :1], reference, LOG_RANGE)[:, 0]
    torch.testing.assert_close(back[sfm > 0], sfm[sfm > 0], rtol=1e-5, atol=0)
    # without evidence the reference is 0 and the log state's own one is used instead
    assert float(evidence_reference(torch.zeros(1, 4, 4))[0]) == 0.0
    assert float(log_reference(depth[:1], mask[:1])[0]) > 0


def test_simulated_stereo_is_close_to_the_truth_has_holes_and_nothing_on_the_sky():
    depth, mask, _ = _scene_batch(batch=16)
    stereo = simulate_stereo(depth, mask, torch.Generator().manual_seed(3))
    assert not stereo[~mask].any()
    valid = stereo > 0
    error = (stereo[valid] - depth[valid]).abs() / depth[valid]
    assert float(error.median()) < 0.02 and float(error.max()) < 0.12  # 0.2-2 % spread, correlated
    holes = 1.0 - valid.sum(dim=(1, 2)).float() / mask.sum(dim=(1, 2)).float()
    assert float(holes.min()) >= 0.09 and float(holes.max()) <= 0.95


def test_training_draws_every_kind_of_evidence_and_its_reference_is_the_evidence_median():
    depth, mask, sfm = _scene_batch(batch=64, seed=1)
    evidence, reference, modes = draw_evidence(depth, mask, sfm, torch.Generator().manual_seed(0), LOG_RANGE)
    assert set(modes) == set(EVIDENCE_MODES)
    for index, mode in enumerate(modes):
        has_sfm, has_stereo = bool(evidence[index, 1].any()), bool(evidence[index, 3].any())
        assert has_sfm == (mode in ("sfm", "sfm_stereo"))
        assert has_stereo == (mode in ("stereo", "sfm_stereo"))
        if has_sfm:  # thinned, never invented
            assert not (evidence[index, 1].bool() & ~(sfm[index] > 0)).any()
        if mode == "none":
            assert float(reference[index]) == pytest.approx(float(log_reference(depth[index:index + 1],
                                                                                 mask[index:index + 1])[0]))
        else:
            values = [depth_from_state(evidence[index:index + 1, c:c + 1], reference[index:index + 1], LOG_RANGE)
                      [0, 0][evidence[index, c + 1].bool()] for c in (0, 2)]
            assert float(reference[index]) == pytest.approx(float(torch.cat(values).median()), rel=1e-4)


def test_evidence_reaches_the_output_and_dropped_evidence_still_gives_a_valid_map():
    torch.manual_seed(0)
    model, diffusion = build_model(completion_config())
    for parameter in list(model.depth_branch.output.parameters()) + list(model.normal_branch.output.parameters()):
        torch.nn.init.normal_(parameter, std=0.1)  # zero-initialised: give the outputs a response
    views = torch.rand(1, 9, 16, 24) * 2 - 1
    depth, mask, sfm = _scene_batch(batch=1)
    reference = evidence_reference(sfm)
    evidence = encode_evidence(sfm, torch.zeros_like(sfm), reference, LOG_RANGE)
    with torch.no_grad():
        with_evidence = diffusion.sample(model, views, evidence=evidence, return_sky=True)
        without = diffusion.sample(model, views, return_sky=True)
        zeros = diffusion.sample(model, views, evidence=torch.zeros_like(evidence), return_sky=True)
    for a, b in zip(with_evidence, without):
        assert a.shape == b.shape and torch.isfinite(a).all() and torch.isfinite(b).all()
    assert (with_evidence[0] - without[0]).abs()[0, 0][sfm[0] > 0].max() > 1e-3  # depth follows the evidence
    assert (with_evidence[1] - without[1]).abs().max() > 1e-4  # so do the normals
    for a, b in zip(without, zeros):  # no evidence = all-zero evidence channels
        torch.testing.assert_close(a, b)
    sky = with_evidence[2]
    assert sky.shape == (1, 1, 16, 24) and float(sky.min()) >= 0.0 and float(sky.max()) <= 1.0


def test_a_network_without_evidence_inputs_refuses_evidence_and_evidence_needs_the_log_state():
    model, _ = build_model(completion_config(evidence=False, sky=False))
    with pytest.raises(ValueError, match="without evidence"):
        model(torch.zeros(1, 9, 16, 24), torch.zeros(1, 1, 16, 24), torch.zeros(1, 3, 16, 24),
              torch.zeros(1, dtype=torch.long), evidence=torch.zeros(1, 4, 16, 24))
    config = completion_config()
    config.diffusion.depth_state = "affine"
    with pytest.raises(ConfigError, match="log depth state"):
        config.validate()


@pytest.mark.parametrize("prediction", ["regression", "v"])
def test_an_evidence_and_sky_network_learns_a_fixed_batch(prediction):
    torch.manual_seed(0)
    config = completion_config(prediction)
    model, diffusion = build_model(config)
    depth, mask, sfm = _scene_batch(batch=4, height=16, width=24)
    rng = np.random.default_rng(0)
    arrays = {"views": rng.integers(0, 255, (4, 9, 16, 24), dtype=np.uint8), "depth": depth.numpy(),
              "normal": np.broadcast_to(np.array([0.0, -1.0, 0.0], np.float32)[None, :, None, None],
                                        (4, 3, 16, 24)).copy(),
              "mask": mask.numpy(), "sfm_depth": sfm.numpy()}
    data = training_tensors(arrays, "log", LOG_RANGE)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    index = torch.arange(4)
    losses, sky_losses = [], []
    for step in range(60):
        generator = torch.Generator().manual_seed(step)
        batch = evidence_batch(data, index, False, config, generator)
        target = batch.pop("depth")
        assert target.shape == (4, 1, 16, 24) and batch["sky"].shape == (4, 1, 16, 24)
        loss, parts = diffusion.training_loss(model, data["views"], target, data["normal"], generator=generator,
                                              **batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
        sky_losses.append(parts["sky"])
    assert np.mean(losses[-10:]) < 0.6 * np.mean(losses[:5])
    assert np.mean(sky_losses[-10:]) < 0.5 * sky_losses[0]  # the sky head learns the top rows
    # evaluation with the shard's points: metric depth scored unaligned, and the sky IoU
    scores = evaluate_arrays(model.eval(), diffusion, arrays, evidence_mode="sfm")
    assert {"abs_rel", "abs_rel_metric", "delta1_metric", "sky_iou"} <= set(scores[0])


def test_evaluation_evidence_and_the_sky_iou():
    depth, mask, sfm = _scene_batch(batch=1)
    arrays = {"depth": depth.numpy(), "sfm_depth": sfm.numpy()}
    assert arrays_evidence(arrays, 0, "none", LOG_RANGE) == (None, None)
    evidence, reference = arrays_evidence(arrays, 0, "sfm", LOG_RANGE)
    assert evidence.shape == (1, 4, 16, 24) and not evidence[:, 2:].any()
    assert float(reference[0]) == pytest.approx(float(sfm[sfm > 0].median()))
    from esgs.core.errors import DatasetError

    with pytest.raises(DatasetError, match="stereo_depth"):
        arrays_evidence(arrays, 0, "sfm_stereo", LOG_RANGE)
    surface = mask[0].numpy()
    assert sky_iou(np.where(surface, 0.1, 0.9), surface) == 1.0
    half = np.where(surface, 0.1, 0.9)
    half[:, :12] = 0.1  # half of the sky missed
    assert sky_iou(half, surface) == pytest.approx(0.5)
    assert sky_iou(np.zeros((4, 4)), np.ones((4, 4), bool)) is None  # no sky anywhere: says nothing


def _constant_network(tmp_path, state: float, sky_logit: float):
    """A tiny evidence + sky network whose outputs are constants (output weights zero, biases set)."""
    from esgs.core.ndn.checkpoint import save_checkpoint

    config = completion_config()
    config.model.working_size = 48
    model, _ = build_model(config)
    with torch.no_grad():
        model.depth_branch.output.bias.copy_(torch.tensor([state, sky_logit]))
        model.normal_branch.output.bias.copy_(torch.tensor([0.0, 0.0, -1.0]))
    return save_checkpoint(tmp_path / f"weights_{sky_logit:+.0f}.pt", model, config)


def test_written_priors_are_metric_pinned_to_the_labels_and_the_sky_head_marks_the_sky(scene, tmp_path):
    from esgs.core.ndn.infer import write_ndn_priors
    from esgs.core.priors import load_prior_maps, write_prior_maps

    truth = {}
    for index in range(4):  # stereo labels on the lower part of each view: the evidence
        name = f"view_{index:03d}.png"
        gt = load_prior_maps(scene, "gt", name)
        labels = gt.mask.copy()
        labels[:14] = False
        write_prior_maps(scene, "labels", name, depth=np.where(labels, gt.depth, 0).astype(np.float32), mask=labels)
        truth[name] = gt.depth[labels]
    state = 0.2
    write_ndn_priors(scene, _constant_network(tmp_path, state, sky_logit=-5.0))
    for name, labelled in truth.items():
        maps = load_prior_maps(scene, "ndn", name)
        assert not maps.relative_depth and maps.mask.all() and not maps.sky.any()
        # the network says reference x exp(c x 0.2) = 1.65x the labels' median everywhere; pinned to
        # the labels (robust scale and shift), a constant becomes their median: in metres, on them
        np.testing.assert_allclose(maps.depth, np.median(labelled), rtol=0.03)
        assert float(maps.depth.std()) < 1e-3 * float(maps.depth.mean())
    write_ndn_priors(scene, _constant_network(tmp_path, state, sky_logit=5.0))
    maps = load_prior_maps(scene, "ndn", "view_000.png")
    assert maps.sky.all() and not maps.mask.any() and not maps.depth.any()  # the trainer's format: sky, no surface


def test_scene_evidence_reads_the_points_each_view_observes_and_the_stereo_labels(scene):
    """The inference evidence: each view's own SfM observations binned to the working size, and
    the labels (when the scene has them) resized over their valid pixels."""
    from esgs.core.colmap import read_model
    from esgs.core.colmap.io import write_model
    from esgs.core.colmap.model import Point3D
    from esgs.core.ndn.data import scene_triples
    from esgs.core.ndn.infer import scene_evidence
    from esgs.core.priors import load_prior_maps, write_prior_maps

    model = read_model(scene, use_pycolmap=False)
    camera = model.cameras[1]
    fx, fy, cx, cy = camera.params
    gt = load_prior_maps(scene, "gt", "view_000.png")
    # points on the plane seen by images 1 and 2 (the plane is the same in every camera: they move along x)
    pixels = np.array([[10.5, 12.5], [30.5, 20.5], [40.5, 8.5]])
    points, expected = {}, {1: [], 2: []}
    images = {image_id: image for image_id, image in model.images.items()}
    for image_id in (1, 2):
        images[image_id].points2d = np.zeros((0, 2))
        images[image_id].point3d_ids = np.zeros(0, np.int64)
    for index, (u, v) in enumerate(pixels):
        z = float(gt.depth[int(v), int(u)])
        centre_1 = -images[1].translation
        world = centre_1 + z * np.array([(u - cx) / fx, (v - cy) / fy, 1.0])
        track = []
        for image_id in (1, 2):
            camera_point = world + images[image_id].translation
            observed = np.array([fx * camera_point[0] / camera_point[2] + cx, fy * camera_point[1] / camera_point[2] + cy])
            images[image_id].points2d = np.vstack([images[image_id].points2d, observed])
            images[image_id].point3d_ids = np.append(images[image_id].point3d_ids, index + 1)
            track.append((image_id, len(images[image_id].points2d) - 1))
            expected[image_id].append((observed, camera_point[2]))
        points[index + 1] = Point3D(index + 1, world, np.array([90, 90, 90], np.uint8), 0.3,
                                    np.array([t[0] for t in track]), np.array([t[1] for t in track]))
    model.points = points
    write_model(model, scene / "sparse" / "0", overwrite=True)
    triples = scene_triples(scene, 32, 4, with_targets=False)
    width, height = triples.views.shape[-1], triples.views.shape[-2]
    sfm, stereo = scene_evidence(scene, triples)
    assert sfm.shape == stereo.shape == (4, height, width) and not stereo.any()
    for image_id in (3, 4):  # these views observe nothing
        assert not sfm[triples.names.index(images[image_id].name)].any()
    for image_id in (1, 2):
        view = triples.names.index(images[image_id].name)
        assert (sfm[view] > 0).sum() == 3
        for (u, v), z in expected[image_id]:
            # the keypoint's pixel (sparse_depth_map), then that pixel's centre binned to the working size
            row = int((np.floor(v) + 0.5) * height / camera.height)
            column = int((np.floor(u) + 0.5) * width / camera.width)
            assert sfm[view, row, column] == pytest.approx(z, rel=1e-5)
    labels = gt.mask.copy()
    labels[:, :20] = False
    for name in triples.names:
        write_prior_maps(scene, "labels", name, depth=np.where(labels, gt.depth, 0).astype(np.float32), mask=labels)
    _, stereo = scene_evidence(scene, triples)
    assert (stereo > 0).any() and not stereo[:, :, : (20 * width) // camera.width - 1].any()
    inside = stereo[0] > 0
    assert float(np.abs(stereo[0][inside] / np.median(gt.depth[labels]) - 1).max()) < 0.5


def test_a_completion_is_pinned_to_its_view_labels_so_the_pixels_it_fills_continue_them():
    from esgs.core.ndn.infer import pin_to_labels

    rows = np.arange(24, dtype=np.float32)[:, None]
    truth = np.broadcast_to(5.0 + 2.0 * rows, (24, 32)).astype(np.float32)
    predicted = 1.3 * truth + 0.7  # right shape, wrong scale and offset
    labels = np.where(rows < 12, truth, 0.0).astype(np.float32)  # labels only on the upper half
    pinned = pin_to_labels(predicted, labels)
    np.testing.assert_allclose(pinned, truth, rtol=1e-4)  # the lower half, where it fills, too
    few = np.zeros_like(labels)
    few[0, :10] = truth[0, :10]  # 10 labelled pixels: too few to fit, the prediction stays
    np.testing.assert_array_equal(pin_to_labels(predicted, few), predicted)
