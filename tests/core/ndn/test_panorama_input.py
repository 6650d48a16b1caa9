"""One-view triples (--monocular) and how a network trained with them reads panoramas."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from esgs.core.errors import ConfigError
from esgs.core.ndn.checkpoint import load_checkpoint
from esgs.core.ndn.config import NDNModelConfig, NDNTrainConfig
from esgs.core.ndn.data import centre_as_neighbours, scene_triples, write_shard
from esgs.core.ndn.infer import _predict_scene
from esgs.core.ndn.train import train_ndn
from esgs.core.progress import no_progress

from .conftest import make_scene, perturbed_weights, tiny_config


def test_centre_as_neighbours_replaces_only_the_chosen_triples():
    views = torch.arange(2 * 9 * 2 * 3, dtype=torch.float32).reshape(2, 9, 2, 3)
    alone = centre_as_neighbours(views)
    for start in (3, 6):
        assert torch.equal(alone[:, start:start + 3], views[:, :3])
    mixed = centre_as_neighbours(views, torch.tensor([True, False]))
    assert torch.equal(mixed[0], alone[0]) and torch.equal(mixed[1], views[1])


def test_scene_triples_knows_a_scene_shot_from_one_centre(tmp_path):
    assert not scene_triples(make_scene(tmp_path / "line", with_gt=False), 32, 2, with_targets=False).one_centre
    panorama = scene_triples(make_scene(tmp_path / "pano", with_gt=False, panorama=True), 32, 2, with_targets=False)
    assert panorama.one_centre


def test_training_with_one_view_triples_sets_the_panorama_input(tmp_path):
    scene = make_scene(tmp_path / "scene", seed=0)
    write_shard(tmp_path / "data" / "shards" / "train_plane_1.npz", scene_triples(scene, 32, 2), {})
    settings = dict(steps=2, batch_size=2, checkpoint_every=2, seed=0, threads=1, validation_triples=0, crop_zoom=0.0)
    assert NDNTrainConfig().monocular == 0.3  # the shipped normals network's fine-tune (docs/ndn.md)
    for name, monocular in (("plain", 0.0), ("alone", 1.0)):
        train_ndn(tmp_path / "data", tmp_path / name, NDNTrainConfig(**settings, monocular=monocular), tiny_config())
    configs = {name: load_checkpoint(tmp_path / name / "checkpoints" / "step_0000002.pt")[2] for name in ("plain", "alone")}
    assert (configs["plain"].model.panorama_input, configs["alone"].model.panorama_input) == ("neighbours", "centre")
    plain, alone = (torch.load(tmp_path / name / "checkpoints" / "step_0000002.pt", weights_only=True)["model"]
                    for name in ("plain", "alone"))
    assert any(not torch.equal(plain[key], alone[key]) for key in plain)
    with pytest.raises(ConfigError, match="monocular"):
        NDNTrainConfig(monocular=-0.5).validate()
    with pytest.raises(ConfigError, match="panorama_input"):
        NDNModelConfig(panorama_input="left").validate()


@pytest.mark.parametrize("panorama", [False, True])
def test_a_network_that_reads_one_view_gets_the_centre_three_times_only_on_panoramas(tmp_path, panorama):
    scene = make_scene(tmp_path / "scene", with_gt=False, panorama=panorama)
    base = tiny_config("regression")
    weights = {}
    for reads in ("neighbours", "centre"):
        config = dataclasses.replace(base, model=dataclasses.replace(base.model, panorama_input=reads))
        weights[reads] = perturbed_weights(tmp_path / f"{reads}.pt", config, 0.05)
    states = {reads: _predict_scene(scene, path, steps=None, seed=0, batch_size=4, stage="t", progress=no_progress)
              .depth_states for reads, path in weights.items()}
    # the same weights: the two predictions differ exactly when the input does
    assert np.array_equal(states["neighbours"], states["centre"]) != panorama
    if panorama:  # and what it read was the centre view three times
        model, diffusion, _, _ = load_checkpoint(weights["centre"])
        triples = scene_triples(scene, 32, 2, with_targets=False)
        views = centre_as_neighbours(torch.from_numpy(triples.views.astype(np.float32) / 127.5 - 1.0))
        expected = diffusion.sample(model, views, seed=0)[0].numpy()
        np.testing.assert_allclose(states["centre"], expected, atol=1e-6)
