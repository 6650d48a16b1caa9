"""NDN data: working sizes, neighbour choice, depth states, shards, split planning."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from esgs.core.errors import DatasetError
from esgs.core.ndn.data import (HELDOUT_SEED_OFFSET, depth_to_state, load_shards, neighbour_indices, plan_scenes,
                                scene_triples, state_to_relative_depth, working_shape, write_shard)
from esgs.core.ndn.infer import depth_metrics, normal_metrics
from esgs.core.ndn.train import flip_horizontally, training_tensors
from esgs.core.priors.losses import fit_scale_shift


def test_working_shape_keeps_the_long_side_and_multiples():
    assert working_shape(1920, 1080, 128, 8) == (128, 72)
    assert working_shape(64, 36, 64, 4) == (64, 36)
    assert working_shape(100, 300, 128, 8) == (40, 128)


def test_neighbours_are_the_closest_cameras_looking_the_same_way():
    centres = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [1.1, 0, 0]])
    directions = np.tile([0.0, 0, 1], (5, 1))
    directions[4] = [0.0, 0, -1]  # close to camera 1 but looking the other way
    neighbours = neighbour_indices(centres, directions)
    assert set(neighbours[0]) == {1, 2}
    assert set(neighbours[1]) == {0, 2}
    assert set(neighbours[3]) == {2, 1}
    single = neighbour_indices(np.zeros((1, 3)), np.array([[0.0, 0, 1]]))
    np.testing.assert_array_equal(single, [[0, 0]])


def test_relative_depth_is_affine_in_depth_and_alignment_recovers_it():
    rng = np.random.default_rng(0)
    depth = rng.uniform(2.0, 30.0, (12, 16)).astype(np.float32)
    mask = np.ones_like(depth, bool)
    mask[:3] = False
    state = depth_to_state(depth, mask)
    assert state[mask].min() == pytest.approx(-1) and state[mask].max() == pytest.approx(1)
    assert (state[~mask] == 1).all()  # no surface reads as far
    relative = torch.from_numpy(state_to_relative_depth(state))
    truth = torch.from_numpy(depth)
    scale, shift = fit_scale_shift(relative, truth, torch.from_numpy(mask))
    torch.testing.assert_close(scale * relative[mask] + shift, truth[mask], atol=1e-3, rtol=1e-4)
    # a known transform of the truth is recovered by the alignment inside the metrics
    scores = depth_metrics(0.37 * truth + 5.0, truth, torch.from_numpy(mask))
    assert scores["abs_rel"] < 1e-5 and scores["delta1"] == 1.0
    # and a wrong depth is scored as wrong
    scrambled = torch.from_numpy(rng.permutation(depth.ravel()).reshape(depth.shape))
    assert depth_metrics(scrambled, truth, torch.from_numpy(mask))["abs_rel"] > 0.2


def test_normal_metrics_measure_angles():
    truth = torch.zeros(3, 2, 2)
    truth[2] = 1
    tilted = truth.clone()
    tilted[0] = np.tan(np.radians(20.0))  # 20 degrees off
    mask = torch.ones(2, 2, dtype=torch.bool)
    assert normal_metrics(truth * 2.0, truth, mask) == pytest.approx({"normal_mean_deg": 0.0, "normal_within_11_25": 1.0},
                                                                       abs=1e-3)
    scores = normal_metrics(tilted, truth, mask)
    assert scores["normal_mean_deg"] == pytest.approx(20.0, abs=1e-3) and scores["normal_within_11_25"] == 0.0


def test_shards_round_trip_from_a_scene_folder(scene, tmp_path):
    triples = scene_triples(scene, 32, 2)
    assert triples.views.shape == (4, 9, 18, 32) and triples.views.dtype == np.uint8
    assert triples.depth.shape == (4, 18, 32) and triples.normal.shape == (4, 3, 18, 32)
    # the first two rows of the source are sky: the mask keeps them out, depth 0 there
    assert not triples.mask[:, 0].any() and triples.mask[:, 3:].all()
    assert (triples.depth[~triples.mask] == 0).all()
    np.testing.assert_allclose(np.linalg.norm(triples.normal, axis=1)[triples.mask], 1.0, atol=1e-5)
    # channels 3-8 are the two neighbours' images (view 0's neighbours on a line: 1 and 2)
    np.testing.assert_array_equal(triples.views[0, 3:6], triples.views[1, :3])
    write_shard(tmp_path / "data" / "shards" / "train_x_1.npz", triples, {"preset": "x"})
    arrays = load_shards(tmp_path / "data", "train")
    np.testing.assert_array_equal(arrays["views"], triples.views)
    np.testing.assert_array_equal(arrays["depth"], triples.depth)
    with pytest.raises(DatasetError, match="no 'heldout' shards"):
        load_shards(tmp_path / "data", "heldout")
    tensors = training_tensors(arrays)
    assert tensors["views"].min() >= -1 and tensors["views"].max() <= 1
    views, depth, normal = flip_horizontally(tensors["views"], tensors["depth"], tensors["normal"])
    torch.testing.assert_close(normal[:, 0], -tensors["normal"][:, 0].flip(-1))
    torch.testing.assert_close(normal[:, 1:], tensors["normal"][:, 1:].flip(-1))


def test_held_out_seeds_never_appear_in_training():
    plan = plan_scenes(14, 3, heldout_presets=("rover_horizon",))
    train = [(p, s) for split, p, s in plan if split == "train"]
    heldout = [(p, s) for split, p, s in plan if split == "heldout"]
    assert len(train) == 14 and len(heldout) == 3 and len(set(train)) == 14
    assert all(s < HELDOUT_SEED_OFFSET for _, s in train) and all(s >= HELDOUT_SEED_OFFSET for _, s in heldout)
    assert "rover_horizon" not in {p for p, _ in train}


def test_build_data_resumes_and_checks_its_settings(scene, tmp_path, monkeypatch):
    from esgs.core.errors import ConfigError
    from esgs.core.ndn import data as data_module

    out = tmp_path / "data"
    triples = scene_triples(scene, 32, 2)
    write_shard(out / "shards" / "train_dune_field_1.npz", triples, {})  # left by an interrupted build
    rendered, palettes = [], []

    def fake_render(preset, seed, *, out, **settings):
        # stands in for the Blender scene render: copy the fixture scene to out
        import shutil

        rendered.append((preset, seed))
        palettes.append(settings["palette"])
        shutil.copytree(scene, out)
        return out

    monkeypatch.setattr(data_module, "render_scene", fake_render)
    manifest = data_module.build_dataset(out, 2, heldout=1, presets=("dune_field", "rocky_slope"), working_size=32,
                                         multiple=2, palette="varied")
    assert palettes == ["varied", "varied"] and manifest["palette"] == "varied"
    assert rendered == [("rocky_slope", 1), ("dune_field", HELDOUT_SEED_OFFSET)]  # the existing shard is skipped
    assert sorted(p.name for p in (out / "shards").iterdir()) == [
        "heldout_dune_field_100000.npz", "train_dune_field_1.npz", "train_rocky_slope_1.npz"]
    assert len(manifest["scenes"]) == 3 and not [p for p in out.iterdir() if p.name.startswith(".")]
    assert load_shards(out, "heldout")["views"].shape == (4, 9, 18, 32)
    with pytest.raises(ConfigError, match="built with --palette varied, not mars"):
        data_module.build_dataset(out, 2, heldout=1, presets=("dune_field", "rocky_slope"), palette="mars")
    with pytest.raises(ConfigError, match="also training presets"):
        data_module.build_dataset(out, 1, presets=("dune_field",), heldout_presets=("dune_field",))
    # a folder from before palettes (no key in its manifest) holds the fixed look: resuming it
    # with today's default look is refused, with the flag that continues it
    manifest.pop("palette")
    (out / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ConfigError, match="built with --palette mars, not varied") as refused:
        data_module.build_dataset(out, 2, heldout=1, presets=("dune_field", "rocky_slope"))
    assert "pass --palette mars to continue it" in str(refused.value)
