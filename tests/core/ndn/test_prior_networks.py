"""Two networks write ``priors/ndn`` by default: depth from one, normals from the other.

Tiny constant networks stand in for the shipped pair, so each written pixel says which network
it came from; the shipped files themselves are checked in test_shipped.py.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from esgs.core.errors import CheckpointError
from esgs.core.formats.imageio import read_depth_exr, write_depth_exr
from esgs.core.formats.scene_dir import SceneDir
from esgs.core.ndn import shipped
from esgs.core.ndn.checkpoint import save_checkpoint
from esgs.core.ndn.train import build_model

from .conftest import tiny_config
from .test_evidence import completion_config


def _constant(path, normal: tuple[float, float, float], *, evidence: bool = False, sky_logit: float = -5.0):
    """A tiny network whose normal output is the constant ``normal`` (its output layer's
    weights zero, biases set); an evidence + sky network has the constant sky logit too."""
    config = completion_config() if evidence else tiny_config("regression")
    config.model.working_size = 48
    model, _ = build_model(config)
    with torch.no_grad():
        for branch in (model.depth_branch, model.normal_branch):
            branch.output.weight.zero_()
        model.normal_branch.output.bias.copy_(torch.tensor(normal))
        if evidence:
            model.depth_branch.output.bias.copy_(torch.tensor([0.0, sky_logit]))
    return save_checkpoint(path, model, config)


@pytest.fixture
def pair(tmp_path, monkeypatch):
    """The package's networks replaced by two constant ones (depth network: normals facing the
    camera; normals network: tilted), no environment overrides."""
    depth = _constant(tmp_path / "depth.pt", (0.0, 0.0, -1.0))
    normals = _constant(tmp_path / "normals.pt", (0.0, -0.6, -0.8), evidence=True)
    monkeypatch.setattr(shipped, "SHIPPED_WEIGHTS", depth)
    monkeypatch.setattr(shipped, "SHIPPED_NORMAL_WEIGHTS", normals)
    monkeypatch.delenv(shipped.WEIGHTS_ENVIRONMENT_VARIABLE, raising=False)
    monkeypatch.delenv(shipped.NORMAL_WEIGHTS_ENVIRONMENT_VARIABLE, raising=False)
    return depth, normals


def test_the_networks_are_the_shipped_pair_unless_named(pair, monkeypatch, tmp_path):
    depth, normals = pair
    assert shipped.resolve_prior_networks() == shipped.PriorNetworks(depth, normals, default=True)
    # a named depth network works alone: a user's model is not mixed with ours
    assert shipped.resolve_prior_networks(tmp_path / "mine.pt") == shipped.PriorNetworks(tmp_path / "mine.pt", None,
                                                                                         default=False)
    assert shipped.resolve_prior_networks(None, "same") == shipped.PriorNetworks(depth, None, default=False)
    assert shipped.resolve_prior_networks(tmp_path / "mine.pt", tmp_path / "n.pt").normals == tmp_path / "n.pt"
    monkeypatch.setenv(shipped.WEIGHTS_ENVIRONMENT_VARIABLE, str(tmp_path / "env.pt"))
    assert shipped.resolve_prior_networks() == shipped.PriorNetworks(tmp_path / "env.pt", None, default=False)
    monkeypatch.setenv(shipped.NORMAL_WEIGHTS_ENVIRONMENT_VARIABLE, str(tmp_path / "env_n.pt"))
    assert shipped.resolve_prior_networks().normals == tmp_path / "env_n.pt"
    monkeypatch.delenv(shipped.WEIGHTS_ENVIRONMENT_VARIABLE)
    monkeypatch.delenv(shipped.NORMAL_WEIGHTS_ENVIRONMENT_VARIABLE)
    monkeypatch.setattr(shipped, "SHIPPED_NORMAL_WEIGHTS", tmp_path / "missing.pt")
    with pytest.raises(CheckpointError, match="normal weights are missing"):
        shipped.resolve_prior_networks()


def test_depth_and_mask_come_from_one_network_and_normals_from_the_other(scene, pair, tmp_path):
    from esgs.core.ndn.infer import ndn_priors_header, write_ndn_priors
    from esgs.core.priors import load_prior_maps

    depth, normals = pair
    write_ndn_priors(scene, depth, normal_weights="same")
    alone = {f"view_{i:03d}.png": load_prior_maps(scene, "ndn", f"view_{i:03d}.png") for i in range(4)}
    assert "normal_weights" not in ndn_priors_header(scene)
    write_ndn_priors(scene)
    tilted = np.array([0.0, -0.6, -0.8])
    for name, single in alone.items():
        maps = load_prior_maps(scene, "ndn", name)
        assert maps.mask.any()
        np.testing.assert_array_equal(maps.mask, single.mask)  # the depth network's surface
        np.testing.assert_array_equal(maps.depth, single.depth)  # and its depth
        np.testing.assert_allclose(single.normal[single.mask], np.broadcast_to([0, 0, -1.0], (single.mask.sum(), 3)),
                                   atol=1e-5)
        np.testing.assert_allclose(maps.normal[maps.mask], np.broadcast_to(tilted, (maps.mask.sum(), 3)), atol=1e-4)
    header = ndn_priors_header(scene)
    assert header["networks"] == "default"
    assert header["weights"] == str(depth) and header["normal_weights"] == str(normals)
    assert header["weights_sha"] == shipped.weights_digest(depth) != header["normal_weights_sha"]
    # the normals network's own depth is kept as the second depth, on the depth network's surface
    assert header["second_depth"] == "normals network"
    write_ndn_priors(scene, normals, normal_weights="same")
    own = {name: load_prior_maps(scene, "ndn", name) for name in alone}
    write_ndn_priors(scene)
    for name, single in alone.items():
        assert single.second_depth is None  # one network: no second opinion
        maps = load_prior_maps(scene, "ndn", name)
        assert maps.second_depth is not None and (maps.second_depth[maps.mask] > 0).all()
        np.testing.assert_allclose(maps.second_depth, np.where(maps.mask, own[name].depth, 0.0), rtol=1e-6)
        assert maps.second_relative_depth == own[name].relative_depth


def test_where_the_normals_network_sees_sky_the_depth_networks_normals_stay(scene, pair, tmp_path):
    from esgs.core.ndn.infer import write_ndn_priors
    from esgs.core.priors import load_prior_maps

    depth, _ = pair
    sky_everywhere = _constant(tmp_path / "sky.pt", (0.0, -0.6, -0.8), evidence=True, sky_logit=5.0)
    write_ndn_priors(scene, depth, normal_weights=sky_everywhere, sky_from_normals=False)
    maps = load_prior_maps(scene, "ndn", "view_000.png")
    # the depth network's mask and sky (it has no sky head: none) are kept; its normals too
    assert maps.mask.any()
    assert maps.sky is None or not maps.sky.any()
    np.testing.assert_allclose(maps.normal[maps.mask], np.broadcast_to([0, 0, -1.0], (maps.mask.sum(), 3)), atol=1e-5)
    # by default the normals network's sky is written as sky, in the trainer's format: no surface there
    write_ndn_priors(scene, depth, normal_weights=sky_everywhere)
    maps = load_prior_maps(scene, "ndn", "view_000.png")
    assert maps.sky.all() and not maps.mask.any() and not maps.depth.any() and not maps.normal.any()


def test_priors_of_the_package_are_outdated_when_its_networks_change_and_auto_predicts_again(scene, pair,
                                                                                              monkeypatch, tmp_path):
    from esgs.core.ndn.infer import ndn_priors_header, outdated_ndn_priors, write_ndn_priors
    from esgs.core.priors import auto
    from esgs.core.priors.io import load_prior_maps, write_prior_maps

    depth, normals = pair
    write_ndn_priors(scene)
    assert outdated_ndn_priors(scene) is None
    # priors of the package's pair from before its normals network marked the sky
    write_ndn_priors(scene, sky_from_normals=False)
    assert "marks the sky" in outdated_ndn_priors(scene)
    write_ndn_priors(scene)
    # priors of the pair from before the normals network's depth was kept are kept (only the
    # opt-in blend reads it)
    for index in range(4):
        SceneDir(scene).second_depth_map("ndn", f"view_{index:03d}.png").unlink()
    header_path = sorted(SceneDir(scene).prior_maps("ndn", "depth").glob("*.exr"))[0]  # the header read
    old_depth, old_header = read_depth_exr(header_path)
    write_depth_exr(header_path, old_depth, metadata={k: v for k, v in old_header.items() if k != "second_depth"})
    assert outdated_ndn_priors(scene) is None
    write_ndn_priors(scene)
    # the package ships other normal weights: the same path, other contents
    _constant(normals, (0.0, 0.6, -0.8), evidence=True)
    assert "changed" in outdated_ndn_priors(scene)
    # ... but a user's own choice is kept, and so is everything while the environment names weights
    write_ndn_priors(scene, depth, normal_weights=normals)
    assert ndn_priors_header(scene)["networks"] == "chosen" and outdated_ndn_priors(scene) is None
    write_ndn_priors(scene, depth, normal_weights="same")
    assert outdated_ndn_priors(scene) is None
    monkeypatch.setenv(shipped.WEIGHTS_ENVIRONMENT_VARIABLE, str(depth))
    assert outdated_ndn_priors(scene) is None
    monkeypatch.delenv(shipped.WEIGHTS_ENVIRONMENT_VARIABLE)
    # a folder from before the normals network shipped: the package's depth network alone, and
    # headers without the digests
    for index in range(4):
        name = f"view_{index:03d}.png"
        old = load_prior_maps(scene, "ndn", name)
        write_prior_maps(scene, "ndn", name, depth=old.depth, normal=old.normal, mask=old.mask, relative_depth=True,
                         units="relative", metadata={"method": "ndn", "weights": str(depth)}, mask_kind="surface")
    assert set(ndn_priors_header(scene)).isdisjoint({"networks", "weights_sha", "normal_weights"})
    assert outdated_ndn_priors(scene) is not None
    # auto notices and predicts again with the pair (labels off: no bpy in this test)
    events = []
    auto.ensure_auto_priors(scene, events.append, settings=auto.AutoPriorSettings(labels=False))
    assert any("computing ndn priors (the package's NDN weights changed" in (e.message or "") for e in events)
    assert ndn_priors_header(scene)["networks"] == "default" and outdated_ndn_priors(scene) is None
    maps = load_prior_maps(scene, "ndn", "view_000.png")
    np.testing.assert_allclose(maps.normal[maps.mask], np.broadcast_to([0, 0.6, -0.8], (maps.mask.sum(), 3)), atol=1e-4)


def test_priors_predicted_before_the_stereo_labels_are_predicted_again_once_they_exist(scene, pair):
    from esgs.core.ndn.infer import ndn_priors_header, outdated_ndn_priors, write_ndn_priors
    from esgs.core.priors import load_prior_maps, write_prior_maps

    write_ndn_priors(scene)
    assert ndn_priors_header(scene)["normal_evidence"] == "sfm points" and outdated_ndn_priors(scene) is None
    for index in range(4):
        name = f"view_{index:03d}.png"
        gt = load_prior_maps(scene, "gt", name)
        write_prior_maps(scene, "labels", name, depth=gt.depth, mask=gt.mask)
    assert "stereo labels" in outdated_ndn_priors(scene)
    write_ndn_priors(scene)
    assert ndn_priors_header(scene)["normal_evidence"] == "sfm points + stereo labels"
    assert outdated_ndn_priors(scene) is None


def test_predict_sky_masks_is_the_sky_the_priors_are_written_with(scene, pair, tmp_path):
    from esgs.core.errors import ConfigError
    from esgs.core.formats.imageio import read_image
    from esgs.core.formats.scene_dir import SceneDir
    from esgs.core.ndn.infer import predict_sky_masks
    from esgs.core.priors import load_prior_maps

    depth, _ = pair
    sky_everywhere = _constant(tmp_path / "sky.pt", (0.0, -0.6, -0.8), evidence=True, sky_logit=5.0)
    no_sky = _constant(tmp_path / "ground.pt", (0.0, -0.6, -0.8), evidence=True, sky_logit=-5.0)
    everywhere, nowhere = predict_sky_masks(scene, sky_everywhere), predict_sky_masks(scene, no_sky)
    assert sorted(everywhere) == [f"view_{i:03d}.png" for i in range(4)]
    for name, mask in everywhere.items():
        assert mask.dtype == bool and mask.shape == read_image(SceneDir(scene).image(name)).shape[:2]
        assert mask.all() and not nowhere[name].any()
    # the same masks esgs priors writes with that network as the normals network
    from esgs.core.ndn.infer import write_ndn_priors

    write_ndn_priors(scene, depth, normal_weights=sky_everywhere)
    np.testing.assert_array_equal(load_prior_maps(scene, "ndn", "view_000.png").sky, everywhere["view_000.png"])
    with pytest.raises(ConfigError, match="no sky head"):
        predict_sky_masks(scene, depth)  # the regression network has none
