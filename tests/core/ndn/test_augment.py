"""Photometric augmentation of NDN training triples (--augment): what it changes and what it keeps."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from esgs.core.cli import main
from esgs.core.errors import ConfigError
from esgs.core.ndn.config import NDNTrainConfig
from esgs.core.ndn.data import scene_triples, write_shard
from esgs.core.ndn.train import _gaussian_blur, augment_photometric, train_ndn

from .conftest import make_scene, tiny_config


def _triples(batch: int = 4, size: tuple[int, int] = (24, 40), seed: int = 0) -> torch.Tensor:
    """A batch whose three views of each triple are the same image (so their changes can be compared)."""
    rng = np.random.default_rng(seed)
    view = torch.from_numpy(rng.uniform(-1, 1, (batch, 3, *size)).astype(np.float32))
    return torch.cat([view, view, view], dim=1)


def test_shapes_range_and_seeded_determinism():
    views = _triples()
    a = augment_photometric(views, torch.Generator().manual_seed(3))
    b = augment_photometric(views, torch.Generator().manual_seed(3))
    c = augment_photometric(views, torch.Generator().manual_seed(4))
    assert a.shape == views.shape and a.dtype == views.dtype
    assert float(a.min()) >= -1.0 and float(a.max()) <= 1.0
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert not torch.equal(a, c) and not torch.equal(a, views)


def test_the_three_views_of_a_triple_change_alike():
    out = augment_photometric(_triples(batch=6), torch.Generator().manual_seed(0))
    torch.testing.assert_close(out[:, 0:3], out[:, 3:6], rtol=0, atol=1e-6)
    torch.testing.assert_close(out[:, 0:3], out[:, 6:9], rtol=0, atol=1e-6)


def test_gray_makes_the_channels_equal_and_no_gray_keeps_colour():
    views = _triples(batch=3)
    gray = augment_photometric(views, torch.Generator().manual_seed(0), gray_probability=1.0, max_blur_sigma=0.0)
    for start in (0, 3, 6):
        torch.testing.assert_close(gray[:, start], gray[:, start + 1], rtol=0, atol=1e-6)
        torch.testing.assert_close(gray[:, start], gray[:, start + 2], rtol=0, atol=1e-6)
    colour = augment_photometric(views, torch.Generator().manual_seed(0), gray_probability=0.0, max_blur_sigma=0.0)
    assert float((colour[:, 0] - colour[:, 1]).abs().max()) > 0.1


def test_blur_matches_opencv_and_keeps_a_constant_image():
    rng = np.random.default_rng(1)
    image = rng.uniform(0, 1, (3, 30, 44)).astype(np.float32)
    for sigma in (0.8, 1.5):
        ours = _gaussian_blur(torch.from_numpy(image), sigma).numpy()
        radius = int(np.ceil(3 * sigma))
        reference = np.stack([cv2.GaussianBlur(channel, (2 * radius + 1, 2 * radius + 1), sigma,
                                               borderType=cv2.BORDER_REFLECT_101) for channel in image])
        np.testing.assert_allclose(ours, reference, atol=1e-5)
    flat = torch.full((2, 10, 12), 0.4)
    torch.testing.assert_close(_gaussian_blur(flat, 1.2), flat)
    torch.testing.assert_close(_gaussian_blur(flat, 0.1), flat, rtol=0, atol=0)  # below 0.3 px: untouched


def test_config_checks_the_probability():
    with pytest.raises(ConfigError, match="augment"):
        NDNTrainConfig(augment=1.5).validate()
    NDNTrainConfig(augment=0.5).validate()


def test_training_with_augmentation_runs_and_differs(tmp_path):
    scene = make_scene(tmp_path / "scene", seed=0)
    write_shard(tmp_path / "data" / "shards" / "train_plane_1.npz", scene_triples(scene, 32, 2), {})
    settings = dict(steps=3, batch_size=2, checkpoint_every=3, seed=0, threads=1, validation_triples=0)
    train_ndn(tmp_path / "data", tmp_path / "plain", NDNTrainConfig(**settings), tiny_config())
    train_ndn(tmp_path / "data", tmp_path / "again", NDNTrainConfig(**settings, augment=0.0), tiny_config())
    augmented = train_ndn(tmp_path / "data", tmp_path / "augmented", NDNTrainConfig(**settings, augment=1.0),
                          tiny_config())
    assert augmented["steps"] == 3 and np.isfinite(augmented["final_loss_mean_last_50"])
    weights = {name: torch.load(tmp_path / name / "checkpoints" / "step_0000003.pt", weights_only=True)["model"]
               for name in ("plain", "again", "augmented")}
    # augment 0 draws nothing extra: the run is bit-identical to one without the setting
    for key in weights["plain"]:
        torch.testing.assert_close(weights["plain"][key], weights["again"][key], rtol=0, atol=0)
    assert any(not torch.equal(weights["plain"][key], weights["augmented"][key]) for key in weights["plain"])


def test_crop_and_zoom_is_the_identity_at_full_scale_and_keeps_map_values():
    from esgs.core.ndn.train import crop_and_zoom

    views = _triples(batch=3, size=(18, 32))
    depth = torch.from_numpy(np.random.default_rng(2).integers(0, 5, (3, 1, 18, 32)).astype(np.float32))
    same, maps = crop_and_zoom(views, {"depth": depth}, torch.Generator().manual_seed(0), min_scale=1.0)
    torch.testing.assert_close(same, views, rtol=0, atol=1e-5)
    torch.testing.assert_close(maps["depth"], depth, rtol=0, atol=0)
    zoomed, maps = crop_and_zoom(views, {"depth": depth}, torch.Generator().manual_seed(0), min_scale=0.5)
    assert zoomed.shape == views.shape and maps["depth"].shape == depth.shape
    # nearest for maps: every value is one the input held (no blend across a depth edge)
    assert set(maps["depth"].unique().tolist()) <= set(depth.unique().tolist())
    assert not torch.equal(maps["depth"], depth)
    # a triple's three views share the window
    torch.testing.assert_close(zoomed[:, 0:3], zoomed[:, 3:6], rtol=0, atol=0)


def test_crop_and_zoom_shows_the_window_it_drew():
    from esgs.core.ndn.train import crop_and_zoom

    # a ramp in x and y: the zoomed image must be the ramp over a sub-window, scaled up
    height, width = 20, 40
    y, x = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                          indexing="ij")
    views = torch.stack([x / width] * 9)[None]
    rows = torch.stack([y])[None]
    zoomed, maps = crop_and_zoom(views, {"rows": rows}, torch.Generator().manual_seed(5), min_scale=0.5)
    columns = zoomed[0, 0, height // 2]
    step = float((columns[1:] - columns[:-1])[2:-2].mean()) * width  # source pixels per output pixel
    assert 0.5 <= step < 1.0 - 1e-3
    # the rows map spans the same share of the image height, within one pixel
    span = float(maps["rows"][0, 0, -1, 0] - maps["rows"][0, 0, 0, 0])
    assert abs(span - step * (height - 1)) <= 1.0 + 1e-6


def test_training_with_crop_and_zoom_runs_and_the_default_crops(tmp_path):
    scene = make_scene(tmp_path / "scene", seed=0)
    write_shard(tmp_path / "data" / "shards" / "train_plane_1.npz", scene_triples(scene, 32, 2), {})
    settings = dict(steps=3, batch_size=2, checkpoint_every=3, seed=0, threads=1, validation_triples=0)
    assert NDNTrainConfig().crop_zoom == 0.5  # the measured choice (docs/ndn.md)
    arms = (("zero", 0.0), ("zero_again", 0.0), ("default", None), ("crop", 1.0))
    for name, crop in arms:
        extra = {} if crop is None else {"crop_zoom": crop}
        result = train_ndn(tmp_path / "data", tmp_path / name, NDNTrainConfig(**settings, **extra), tiny_config())
        assert np.isfinite(result["final_loss_mean_last_50"])
    weights = {name: torch.load(tmp_path / name / "checkpoints" / "step_0000003.pt", weights_only=True)["model"]
               for name, _ in arms}
    for key in weights["zero"]:  # no crops drawn: the run is reproducible bit for bit
        torch.testing.assert_close(weights["zero"][key], weights["zero_again"][key], rtol=0, atol=0)
    for name in ("default", "crop"):
        assert any(not torch.equal(weights["zero"][key], weights[name][key]) for key in weights["zero"])
    with pytest.raises(ConfigError, match="crop_zoom"):
        NDNTrainConfig(crop_zoom=-0.1).validate()


def test_resume_keeps_the_runs_saved_settings_unless_a_flag_overrides_them(tmp_path):
    scene = make_scene(tmp_path / "scene", seed=0)
    data = tmp_path / "data"
    write_shard(data / "shards" / "train_plane_1.npz", scene_triples(scene, 32, 2), {})
    out = tmp_path / "model"
    tiny = ["--base-channels", "8", "--levels", "2", "--time-dim", "16", "--working-size", "32", "--timesteps", "50",
            "--sample-steps", "2", "--batch-size", "2", "--checkpoint-every", "1", "--threads", "1"]

    def saved() -> dict:
        return json.loads((out / "config.json").read_text())["train"]

    assert main(["ndn", "train", str(data), "--out", str(out), "--steps", "1", "--crop-zoom", "0", "--augment", "0.2",
                 *tiny]) == 0
    # resumed without the flags: the run's own settings, not today's defaults
    assert main(["ndn", "train", str(data), "--out", str(out), "--steps", "2", "--resume", *tiny]) == 0
    assert (saved()["crop_zoom"], saved()["augment"], saved()["steps"]) == (0.0, 0.2, 2)
    # a flag given on the resuming command line wins
    assert main(["ndn", "train", str(data), "--out", str(out), "--steps", "3", "--resume", "--crop-zoom", "0.25",
                 *tiny]) == 0
    assert (saved()["crop_zoom"], saved()["augment"]) == (0.25, 0.2)
    # a run saved before a setting existed resumes with the value it trained with (crop_zoom 0 then)
    config = json.loads((out / "config.json").read_text())
    del config["train"]["crop_zoom"]
    (out / "config.json").write_text(json.dumps(config))
    assert main(["ndn", "train", str(data), "--out", str(out), "--steps", "4", "--resume", *tiny]) == 0
    assert saved()["crop_zoom"] == 0.0
    # a new folder (no --resume) takes the defaults
    assert main(["ndn", "train", str(data), "--out", str(tmp_path / "fresh"), "--steps", "1", *tiny]) == 0
    assert json.loads((tmp_path / "fresh" / "config.json").read_text())["train"]["crop_zoom"] == 0.5


def test_an_unreadable_saved_config_is_a_clear_error(tmp_path):
    from esgs.core.ndn.train import saved_train_config

    assert saved_train_config(tmp_path) is None
    (tmp_path / "config.json").write_text("{not json")
    with pytest.raises(ConfigError, match="cannot read the run's training settings") as err:
        saved_train_config(tmp_path)
    assert "config.json" in str(err.value)
