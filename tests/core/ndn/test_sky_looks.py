"""Repainted skies for NDN training (--sky-looks): which pixels change, which never do, and the run."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from esgs.core.errors import ConfigError
from esgs.core.ndn.config import NDNModelConfig, NDNTrainConfig
from esgs.core.ndn.data import SHARD_FORMAT, load_shards
from esgs.core.ndn.sky_looks import relight_sky, sky_of_views
from esgs.core.ndn.train import train_ndn

from .conftest import tiny_config

HEIGHT, WIDTH = 16, 32


def _shard_arrays(count: int = 4, seed: int = 0) -> dict[str, np.ndarray]:
    """One scene's triples: ``count`` distinct views, each the centre of one triple whose
    neighbours are the next two views; view i has sky in its top i + 2 rows."""
    rng = np.random.default_rng(seed)
    images = rng.integers(0, 256, (count, 3, HEIGHT, WIDTH), dtype=np.uint8)
    mask = np.ones((count, HEIGHT, WIDTH), bool)
    for index in range(count):
        mask[index, :index + 2] = False
    views = np.stack([np.concatenate([images[i], images[(i + 1) % count], images[(i + 2) % count]])
                      for i in range(count)])
    depth = np.where(mask, 10.0, 0.0).astype(np.float32)
    normal = np.zeros((count, 3, HEIGHT, WIDTH), np.float32)
    normal[:, 2] = -1.0
    return {"views": views, "mask": mask, "depth": depth, "normal": normal * mask[:, None]}


def test_each_neighbours_sky_is_the_mask_of_the_triple_it_is_the_centre_of():
    arrays = _shard_arrays()
    sky, known = sky_of_views(arrays["views"], arrays["mask"])
    assert sky.shape == (4, 3, HEIGHT, WIDTH) and known.all()
    for index in range(4):
        for slot in range(3):
            np.testing.assert_array_equal(sky[index, slot], ~arrays["mask"][(index + slot) % 4])
    # a neighbour that is no centre of the shard: the triple's neighbours' sky is unknown
    foreign = arrays["views"].copy()
    foreign[2, 3:6] = 255 - foreign[2, 3:6]
    sky, known = sky_of_views(foreign, arrays["mask"])
    assert known.tolist() == [True, True, False, True]


def test_only_sky_pixels_change_and_the_ground_is_kept_bit_for_bit():
    arrays = _shard_arrays()
    views = torch.from_numpy(arrays["views"].astype(np.float32) / 127.5 - 1.0)
    sky = torch.from_numpy(sky_of_views(arrays["views"], arrays["mask"])[0])
    out = relight_sky(views, sky, torch.Generator().manual_seed(0), probability=1.0)
    assert out.shape == views.shape and out.dtype == views.dtype
    per_view = out.reshape(4, 3, 3, HEIGHT, WIDTH)
    before = views.reshape(4, 3, 3, HEIGHT, WIDTH)
    ground = ~sky[:, :, None].expand_as(per_view)
    assert torch.equal(per_view[ground], before[ground])
    assert float((per_view - before).abs()[~ground].mean()) > 0.05  # the sky is another one
    assert float(out.min()) >= -1.0 and float(out.max()) <= 1.0
    # one colour for a triple: the three views' sky share the ratio of red to green (their
    # gradients and glare scale all channels alike), away from clipped pixels
    colour = (relight_sky(torch.cat([views] * 4), torch.cat([sky] * 4), torch.Generator().manual_seed(1),
                          probability=1.0).reshape(16, 3, 3, HEIGHT, WIDTH) + 1.0) / 2.0
    checked = 0
    for triple in range(16):
        ratios = []
        for view in range(3):
            pixels = colour[triple, view][:, sky[triple % 4, view]]
            unclipped = (pixels < 0.99).all(0) & (pixels > 0.01).all(0)
            if int(unclipped.sum()) >= 10:
                ratios.append(float((pixels[0, unclipped] / pixels[1, unclipped]).median()))
        if len(ratios) == 3:
            checked += 1
            assert max(ratios) - min(ratios) < 0.05, ratios
    assert checked >= 4


def test_probability_decides_and_the_draws_do_not_depend_on_it():
    arrays = _shard_arrays()
    views = torch.from_numpy(arrays["views"].astype(np.float32) / 127.5 - 1.0)
    sky = torch.from_numpy(sky_of_views(arrays["views"], arrays["mask"])[0])
    generators = [torch.Generator().manual_seed(5) for _ in range(3)]
    assert torch.equal(relight_sky(views, sky, generators[0], probability=0.0), views)
    first = relight_sky(views, sky, generators[1], probability=1.0)
    torch.testing.assert_close(relight_sky(views, sky, generators[2], probability=1.0), first, rtol=0, atol=0)
    # the same number of draws whatever was chosen: a resumed run repeats an uninterrupted one
    assert torch.equal(generators[0].get_state(), generators[1].get_state())
    # no sky known: nothing to repaint
    assert torch.equal(relight_sky(views, torch.zeros_like(sky), torch.Generator(), probability=1.0), views)


def test_load_shards_gives_each_views_sky_only_when_asked(tmp_path):
    arrays = _shard_arrays()
    shards = tmp_path / "data" / "shards"
    shards.mkdir(parents=True)
    np.savez(shards / "train_sky_1.npz", format=np.array(SHARD_FORMAT), names=np.array(["a", "b", "c", "d"]), **arrays)
    assert "view_sky" not in load_shards(tmp_path / "data", "train")
    loaded = load_shards(tmp_path / "data", "train", with_view_sky=True)
    np.testing.assert_array_equal(loaded["view_sky"], sky_of_views(arrays["views"], arrays["mask"])[0])


def test_training_with_new_skies_runs_and_changes_the_weights(tmp_path):
    shards = tmp_path / "data" / "shards"
    shards.mkdir(parents=True)
    arrays = _shard_arrays(count=4)
    np.savez(shards / "train_sky_1.npz", format=np.array(SHARD_FORMAT), names=np.array(["a", "b", "c", "d"]), **arrays)
    base = tiny_config("regression")
    config = dataclasses.replace(base, model=NDNModelConfig(**{**dataclasses.asdict(base.model), "sky": True,
                                                                "working_size": HEIGHT}))
    settings = dict(steps=2, batch_size=4, checkpoint_every=2, seed=0, threads=1, validation_triples=0, crop_zoom=0.0)
    assert NDNTrainConfig().sky_looks == 0.5  # the shipped normals network's fine-tune (docs/ndn.md)
    for name, looks in (("plain", 0.0), ("new_skies", 1.0)):
        result = train_ndn(tmp_path / "data", tmp_path / name, NDNTrainConfig(**settings, sky_looks=looks), config)
        assert np.isfinite(result["final_loss_mean_last_50"])
    weights = {name: torch.load(tmp_path / name / "checkpoints" / "step_0000002.pt", weights_only=True)["model"]
               for name in ("plain", "new_skies")}
    assert any(not torch.equal(weights["plain"][key], weights["new_skies"][key]) for key in weights["plain"])
    with pytest.raises(ConfigError, match="sky_looks"):
        NDNTrainConfig(sky_looks=1.5).validate()
