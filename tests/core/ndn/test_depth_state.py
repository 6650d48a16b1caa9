"""The NDN depth state: affine (the shipped weights) or scale-normalised log depth.

Both invert to a relative depth in the standard prior format (affine in true depth); the log
state spreads its precision by range, which matters on rover views spanning 3 to 110 m.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from esgs.core.cli import main
from esgs.core.config import config_from_dict
from esgs.core.errors import ConfigError
from esgs.core.formats.imageio import read_depth_exr
from esgs.core.ndn.config import NDNConfig, NDNDiffusionConfig, NDNTrainConfig
from esgs.core.ndn.data import (LOG_DEPTH_RANGE, depth_to_state, relative_depth_bounds, scene_triples,
                                state_to_relative_depth, write_shard)
from esgs.core.ndn.infer import evaluate_arrays, maps_from_states, score_view, views_per_batch
from esgs.core.ndn.train import (build_model, checkpoint_config, load_checkpoint, save_checkpoint, train_ndn,
                                 training_tensors)
from esgs.core.priors import load_prior_maps
from esgs.core.priors.losses import fit_scale_shift

from .conftest import perturbed_weights, tiny_config


def _rover_depth(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A rover-like view: depth from 3 m (bottom rows) to 110 m (top rows), a sky strip, noise."""
    rng = np.random.default_rng(seed)
    rows = np.linspace(1.0, 0.0, 40)[:, None]  # 1 at the bottom row
    depth = 3.0 * (110.0 / 3.0) ** (1.0 - rows) * np.exp(rng.normal(0.0, 0.05, (40, 64)))
    depth = np.clip(depth, 3.0, 110.0).astype(np.float32)
    mask = np.ones(depth.shape, bool)
    mask[:3] = False  # sky
    depth[:3] = 0.0
    depth[-1, 0], depth[3, 0] = 3.0, 110.0  # the exact extremes are present
    return depth, mask


def _log_config(config: NDNConfig | None = None) -> NDNConfig:
    config = config or tiny_config()
    return dataclasses.replace(config, diffusion=dataclasses.replace(config.diffusion, depth_state="log"))


def test_log_state_inverts_to_depth_up_to_one_scale():
    depth, mask = _rover_depth()
    state = depth_to_state(depth, mask, "log")
    assert state.dtype == np.float32 and (state[~mask] == 1.0).all()  # no surface reads as far
    # 3-110 m is ln(36.7) = 3.6 wide: centred on the reference it fits inside +-c = +-2.5, unclipped
    assert -1.0 < state[mask].min() < -0.6 and 0.6 < state[mask].max() < 1.0
    np.testing.assert_allclose(depth_to_state(7.3 * depth, mask, "log"), state, atol=1e-6)  # scale-free
    relative = torch.from_numpy(state_to_relative_depth(state, "log"))
    truth, valid = torch.from_numpy(depth), torch.from_numpy(mask)
    scale, shift = fit_scale_shift(relative, truth, valid)
    assert abs(float(shift)) < 1e-3  # metres: one unknown scale, no shift
    aligned = scale * relative[valid] + shift
    assert float(((aligned - truth[valid]).abs() / truth[valid]).max()) < 1e-4
    low, high = relative_depth_bounds("log")
    assert low == pytest.approx(math.exp(-LOG_DEPTH_RANGE)) and high == pytest.approx(math.exp(LOG_DEPTH_RANGE))
    assert low <= float(relative.min()) and float(relative.max()) <= high
    with pytest.raises(ConfigError, match="depth state"):
        depth_to_state(depth, mask, "inverse")


def _error_after_alignment(depth: np.ndarray, mask: np.ndarray, kind: str, state_error: float) -> np.ndarray:
    """Relative depth error per pixel when the state is off by ``state_error`` and the map is
    aligned with the scale/shift that is exact for the true state (e.g. from SfM points)."""
    state = depth_to_state(depth, mask, kind)
    truth, valid = torch.from_numpy(depth), torch.from_numpy(mask)
    scale, shift = fit_scale_shift(torch.from_numpy(state_to_relative_depth(state, kind)), truth, valid)
    wrong = state_to_relative_depth(np.clip(state + state_error, -1.0, 1.0), kind)
    estimate = float(scale) * wrong + float(shift)
    return np.abs(estimate - depth) / np.maximum(depth, 1e-6)


def test_log_state_is_far_more_precise_at_near_range():
    depth, mask = _rover_depth()
    near = mask & (depth <= 3.0 + 1e-6)
    far = mask & (depth >= 110.0 - 1e-4)
    # a state 0.01 too far at the near end (-0.01 at the far end: +0.01 would be clipped there)
    affine_near = _error_after_alignment(depth, mask, "affine", 0.01)[near].max()
    log_near = _error_after_alignment(depth, mask, "log", 0.01)[near].max()
    # affine: 0.01 of the state is 0.01 x 107 m / 2 = 0.535 m, 17.8 % at 3 m; log: e^0.025 - 1 = 2.5 %
    assert affine_near == pytest.approx(0.01 * 107.0 / 2.0 / 3.0, rel=1e-3)
    assert log_near == pytest.approx(math.exp(0.01 * LOG_DEPTH_RANGE) - 1.0, rel=1e-3)
    assert log_near < affine_near / 7.0
    # the price: the same relative error at every range, so the far end is less precise than affine's 0.5 %
    affine_far = _error_after_alignment(depth, mask, "affine", -0.01)[far].max()
    log_far = _error_after_alignment(depth, mask, "log", -0.01)[far].max()
    assert affine_far == pytest.approx(0.01 * 107.0 / 2.0 / 110.0, rel=1e-3)
    assert log_far == pytest.approx(1.0 - math.exp(-0.01 * LOG_DEPTH_RANGE), rel=1e-3)


def test_configs_and_checkpoints_without_the_field_are_affine(tmp_path):
    saved = dataclasses.asdict(tiny_config())
    for key in ("depth_state", "log_depth_range"):
        del saved["diffusion"][key]
    assert config_from_dict(NDNConfig, saved).diffusion.depth_state == "affine"
    model, _ = build_model(tiny_config())
    path = save_checkpoint(tmp_path / "old.pt", model, tiny_config())
    payload = torch.load(path, weights_only=True)
    payload["config"] = saved  # as written before depth_state existed
    torch.save(payload, path)
    assert load_checkpoint(path)[2].diffusion.depth_state == "affine"
    assert checkpoint_config(path) == tiny_config()
    with pytest.raises(ConfigError, match="depth_state"):
        NDNDiffusionConfig(depth_state="inverse").validate()
    with pytest.raises(ConfigError, match="log_depth_range"):
        NDNDiffusionConfig(log_depth_range=0.0).validate()


def test_shipped_weights_are_affine():
    from esgs.core.ndn.shipped import SHIPPED_WEIGHTS

    assert checkpoint_config(SHIPPED_WEIGHTS).diffusion.depth_state == "affine"


def test_inference_and_evaluation_follow_the_checkpoints_depth_state(scene, tmp_path):
    weights = perturbed_weights(tmp_path / "log.pt", _log_config(), 0.05)
    model, diffusion, _, _ = load_checkpoint(weights)
    assert main(["priors", str(scene), "--method", "ndn", "--weights", str(weights), "--steps", "2"]) == 0
    # what write_ndn_priors must have written: the same samples, read as log states
    triples = scene_triples(scene, 32, 2, with_targets=False)
    views = torch.from_numpy(triples.views.astype(np.float32) / 127.5 - 1.0)
    step = views_per_batch(4, diffusion)
    states = [diffusion.sample(model, views[start:start + step], steps=2, seed=start)
              for start in range(0, views.shape[0], step)]
    depth_states = torch.cat([depth for depth, _ in states]).numpy()
    normal_states = torch.cat([normal for _, normal in states]).numpy()
    from esgs.core.formats.imageio import read_image

    for index, name in enumerate(triples.names):
        maps = load_prior_maps(scene, "ndn", name)
        image = read_image(scene / "images" / name)[..., :3]
        expected, _, mask = maps_from_states(depth_states[index, 0], normal_states[index], image, kind="log")
        np.testing.assert_array_equal(maps.mask, mask)
        np.testing.assert_allclose(maps.depth, expected, rtol=1e-3, atol=1e-6)
        affine, _, _ = maps_from_states(depth_states[index, 0], normal_states[index], image)
        assert np.abs(affine - expected)[mask].max() > 0.05  # the affine reading would differ
        _, header = read_depth_exr(scene / "priors/ndn/depth" / f"{name.rsplit('.', 1)[0]}.exr")
        assert header["depth_state"] == "log" and header["depth_kind"] == "relative"
    # evaluation reads states the same way: its scores are those of exp(c x state)
    arrays = scene_triples(scene, 32, 2)
    arrays = {"views": arrays.views[:1], "depth": arrays.depth[:1], "normal": arrays.normal[:1],
              "mask": arrays.mask[:1]}
    scores = evaluate_arrays(model, diffusion, arrays, steps=2, seed=0)[0]
    state, normal = diffusion.sample(model, torch.from_numpy(arrays["views"].astype(np.float32) / 127.5 - 1.0),
                                     steps=2, seed=0)
    expected = score_view(np.exp(LOG_DEPTH_RANGE * state[0, 0].numpy()), normal[0].numpy(), arrays["depth"][0],
                          arrays["normal"][0], arrays["mask"][0])
    assert scores == pytest.approx(expected)


def test_training_targets_resume_and_fine_tuning_keep_the_depth_state(scene, tmp_path):
    data = tmp_path / "data"
    write_shard(data / "shards" / "train_plane_1.npz", scene_triples(scene, 32, 2), {})
    arrays = dict(np.load(data / "shards" / "train_plane_1.npz"))
    log_targets = training_tensors(arrays, "log")["depth"][:, 0].numpy()
    np.testing.assert_array_equal(log_targets[0], depth_to_state(arrays["depth"][0], arrays["mask"][0], "log"))
    settings = NDNTrainConfig(steps=1, batch_size=2, checkpoint_every=1, threads=1, ema_decay=0.0)
    train_ndn(data, tmp_path / "log", settings, _log_config())
    assert load_checkpoint(tmp_path / "log")[2].diffusion.depth_state == "log"
    # resuming or fine-tuning a log checkpoint as affine is refused; keeping it is fine
    with pytest.raises(ConfigError, match="cannot resume .* 'log' .* as depth state 'affine'"):
        train_ndn(data, tmp_path / "log", dataclasses.replace(settings, steps=2), tiny_config(), resume=True)
    init = dataclasses.replace(settings, steps=2, init=str(tmp_path / "log/checkpoints/step_0000001.pt"))
    with pytest.raises(ConfigError, match="cannot fine-tune"):
        train_ndn(data, tmp_path / "tuned", init, tiny_config())
    train_ndn(data, tmp_path / "tuned", init, _log_config())
    assert load_checkpoint(tmp_path / "tuned")[2].diffusion.depth_state == "log"


def test_train_command_depth_state_flag_and_resume(scene, tmp_path, capsys):
    data = tmp_path / "data"
    write_shard(data / "shards" / "train_plane_1.npz", scene_triples(scene, 32, 2), {})
    out = tmp_path / "model"
    tiny = ["--base-channels", "8", "--levels", "2", "--time-dim", "16", "--working-size", "32", "--timesteps", "50",
            "--sample-steps", "2", "--batch-size", "2", "--checkpoint-every", "1", "--threads", "1"]
    assert main(["ndn", "train", str(data), "--out", str(out), "--steps", "1", "--depth-state", "log", *tiny]) == 0
    assert checkpoint_config(out / "checkpoints/step_0000001.pt").diffusion.depth_state == "log"
    # --resume without --depth-state keeps the checkpoint's state
    assert main(["ndn", "train", str(data), "--out", str(out), "--steps", "2", "--resume", *tiny]) == 0
    assert checkpoint_config(out / "checkpoints/step_0000002.pt").diffusion.depth_state == "log"
    capsys.readouterr()
    # asking for another state is a clear error, and nothing is written
    assert main(["ndn", "train", str(data), "--out", str(out), "--steps", "3", "--resume", "--depth-state", "affine",
                 *tiny]) == 2
    assert "cannot resume a checkpoint trained with depth state 'log'" in capsys.readouterr().err
    assert not (out / "checkpoints/step_0000003.pt").exists()
    assert main(["ndn", "train", str(data), "--out", str(tmp_path / "tuned"), "--steps", "3", "--init",
                 str(out / "checkpoints/step_0000002.pt"), "--log-depth-range", "3.0", *tiny]) == 2
    assert "cannot fine-tune" in capsys.readouterr().err
