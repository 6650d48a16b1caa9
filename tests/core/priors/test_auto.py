"""The ``auto`` prior source: the fusion rule on cases with known holes and wrong pixels, the
folder it writes and reads back, its cache, and the confidence reaching the losses."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from esgs.core.colmap import read_model
from esgs.core.formats.scene_dir import PriorSource, SceneDir
from esgs.core.priors import auto
from esgs.core.priors.auto import AutoPriorSettings, ensure_auto_priors, fuse_view, pin_relative_depth
from esgs.core.priors.io import PriorMaps, load_prior_maps, write_prior_maps
from esgs.core.priors.losses import depth_loss, normal_loss
from esgs.core.priors.sfm import write_sfm_priors
from tests.blender.colmap_helpers import synthetic_model, write_scene

H, W = 40, 60


def _truth() -> np.ndarray:
    """A sloping surface 5-8 m away."""
    rows = np.linspace(0.0, 1.0, H, dtype=np.float32)[:, None]
    return (5.0 + 3.0 * rows + 0.2 * np.linspace(0, 1, W, dtype=np.float32)[None, :]).astype(np.float32)


def _sfm(truth: np.ndarray, step: int = 3) -> np.ndarray:
    sparse = np.zeros_like(truth)
    sparse[::step, ::step] = truth[::step, ::step]
    return sparse


def _maps(depth, mask=None, *, relative=False, normal_z=1.0):
    mask = np.ones(depth.shape, bool) if mask is None else mask
    normal = np.zeros((*depth.shape, 3), np.float32)
    normal[..., 2] = normal_z
    return PriorMaps(depth=depth.astype(np.float32), normal=normal, mask=mask, relative_depth=relative)


def test_labels_win_where_they_agree_with_the_points_and_ndn_fills_their_holes():
    truth = _truth()
    hole = np.zeros((H, W), bool)
    hole[10:20, 20:40] = True
    labels = _maps(np.where(hole, 0.0, truth), ~hole, normal_z=1.0)
    ndn = _maps(0.5 * truth + 2.0, relative=True, normal_z=-1.0)  # affine in the truth: pinned exactly
    fused = fuse_view(_sfm(truth), labels, ndn)
    np.testing.assert_allclose(fused.depth, truth, rtol=1e-4)  # every pixel, the hole included
    assert fused.mask.all()
    settings = AutoPriorSettings()
    assert fused.confidence[~hole] == pytest.approx(1.0)  # labels exact: 1 - 0 / max_error
    assert fused.confidence[hole] == pytest.approx(settings.ndn_trust, rel=1e-3)  # NDN pinned exactly, halved trust
    assert (fused.normal[~hole, 2] == 1.0).all() and (fused.normal[hole, 2] == -1.0).all()  # normals follow the source
    assert fused.report["share"]["labels"] == pytest.approx(1 - hole.mean())
    assert fused.report["share"]["ndn"] == pytest.approx(hole.mean())


def test_labels_that_contradict_the_points_are_dropped_and_ndn_trust_falls_with_its_error():
    truth = _truth()
    labels = _maps(1.3 * truth)  # 30 % off the SfM points: beyond max_error 0.15
    noisy = truth * (1.0 + 0.06 * np.sign(np.sin(np.arange(W)))[None, :])  # NDN 6 % off
    fused = fuse_view(_sfm(truth), labels, _maps(noisy, relative=False))
    assert fused.report["labels"]["trust"] == 0.0 and fused.report["share"]["labels"] == 0.0
    expected = 0.5 * (1.0 - fused.report["ndn"]["error"] / 0.15)
    assert 0.0 < expected < 0.5
    np.testing.assert_allclose(fused.confidence, expected, rtol=1e-5)
    np.testing.assert_allclose(fused.depth, noisy, rtol=1e-6)


def test_disagreeing_pixels_halve_the_labels_confidence():
    truth = _truth()
    wrong = np.zeros((H, W), bool)
    wrong[30:, 50:] = True
    ndn = _maps(np.where(wrong, 2.0 * truth, truth))  # NDN wrong in one corner only
    fused = fuse_view(_sfm(truth), _maps(truth), ndn)
    assert fused.confidence[wrong] == pytest.approx(0.5)
    assert fused.confidence[~wrong] == pytest.approx(1.0)
    np.testing.assert_allclose(fused.depth, truth)  # labels' depth is kept; only its weight falls


def test_sfm_is_the_floor_and_sky_pixels_get_no_depth():
    truth = _truth()
    sky = np.zeros((H, W), bool)
    sky[:8] = True
    sparse = _sfm(truth)
    fused = fuse_view(sparse, None, None, sky)
    expected = (sparse > 0) & ~sky
    np.testing.assert_array_equal(fused.mask, expected)
    np.testing.assert_allclose(fused.depth[expected], truth[expected])
    assert (fused.confidence[expected] == 1.0).all() and (fused.normal == 0).all()
    assert fused.report["share"]["sky"] == pytest.approx(sky.mean())
    # a dense source marks no depth on sky pixels either
    fused = fuse_view(sparse, _maps(truth), None, sky)
    assert not fused.mask[sky].any() and fused.mask[~sky].all()


def test_with_the_blend_on_the_holes_of_views_with_sky_take_the_geometric_mean_of_both_depths():
    truth = _truth()
    sky = np.zeros((H, W), bool)
    sky[:4] = True  # above the horizon
    hole = np.zeros((H, W), bool)
    hole[4:14, :] = True  # the far ground under it, beyond the labels
    labels = _maps(np.where(hole | sky, 0.0, truth), ~(hole | sky))
    points = np.where(hole, 0.0, _sfm(truth))  # the points check both networks where they are exact
    near, far = np.where(hole, truth / 1.3, truth), np.where(hole, truth * 1.3, truth)
    ndn = _maps(near)
    ndn.second_depth = far
    # each network's own depth in the hole, as it is
    settings = AutoPriorSettings(hole_fill="pinned", blend_second_depth=True)
    assert not AutoPriorSettings().blend_second_depth  # opt-in (docs/priors.md: measured downstream)
    fused = fuse_view(points, labels, ndn, sky, settings)
    np.testing.assert_allclose(fused.depth[hole], truth[hole], rtol=1e-5)  # sqrt(t / 1.3 * t * 1.3)
    assert not fused.mask[sky].any()
    assert fused.report["blend"]["share"] == pytest.approx(1.0)
    assert fused.report["second"]["trust"] == pytest.approx(settings.ndn_trust)
    # no sky in the view, a smaller sky share than asked, or no second depth: the first network alone
    for view_sky, blend_min_sky, second, blend in ((None, 0.02, far, True), (sky, 0.2, far, True),
                                                   (sky, 0.02, None, True), (sky, 0.02, far, False)):
        ndn.second_depth = second
        alone = fuse_view(points, labels, ndn, view_sky, AutoPriorSettings(
            hole_fill="pinned", blend_min_sky=blend_min_sky, blend_second_depth=blend))
        np.testing.assert_allclose(alone.depth[hole], near[hole], rtol=1e-6)
        assert "blend" not in alone.report
    # a second depth the points contradict is not trusted, so not blended
    ndn.second_depth = far * 1.5
    doubted = fuse_view(points, labels, ndn, sky, settings)
    np.testing.assert_allclose(doubted.depth[hole], near[hole], rtol=1e-6)
    assert doubted.report["second"]["error"] == pytest.approx(0.5, rel=1e-3)
    assert doubted.report["second"]["trust"] == 0.0 and "blend" not in doubted.report
    # a first depth they contradict gives way to a trusted second one, alone; or to nothing
    ndn = _maps(near * 1.5)
    ndn.second_depth = far
    fallback = fuse_view(points, labels, ndn, sky, settings)
    np.testing.assert_allclose(fallback.depth[hole], far[hole], rtol=1e-6)
    assert fallback.report["ndn"]["from"] == "second depth" and "blend" not in fallback.report
    strict = fuse_view(points, labels, ndn, sky, AutoPriorSettings(hole_fill="pinned", blend_second_depth=True,
                                                                   second_depth_fallback=False))
    assert not strict.mask[hole].any() and strict.report["ndn"]["trust"] == 0.0


def test_the_second_depth_is_written_and_read_back_at_the_size_asked(tmp_path):
    truth = _truth()
    names = ("view_000.png",)
    write_prior_maps(tmp_path, "ndn", names[0], depth=truth, mask=np.ones((H, W), bool), relative_depth=True,
                     units="relative", mask_kind="surface", second_depth=2.0 * truth)
    maps = load_prior_maps(tmp_path, "ndn", names[0], size=(W // 2, H // 2))
    assert maps.relative_depth and not maps.second_relative_depth  # each map keeps its own kind
    assert maps.second_depth.shape == maps.depth.shape == (H // 2, W // 2)
    np.testing.assert_allclose(maps.second_depth, 2.0 * maps.depth, rtol=1e-6)
    assert load_prior_maps(tmp_path, "ndn", names[0]).second_depth.shape == (H, W)


def test_a_prediction_that_inverts_near_and_far_is_not_pinned():
    truth = _truth()
    assert pin_relative_depth(20.0 - truth, np.ones((H, W), bool), _sfm(truth)) is None
    assert pin_relative_depth(truth, np.ones((H, W), bool), np.zeros((H, W), np.float32)) is None


# --- the folder -------------------------------------------------------------------------
@pytest.fixture
def scene(tmp_path):
    folder = write_scene(tmp_path, synthetic_model())
    model = read_model(folder)
    for image in model.sorted_images():
        (folder / "images" / image.name).parent.mkdir(parents=True, exist_ok=True)
        (folder / "images" / image.name).write_bytes(b"not read by the fusion")
    write_sfm_priors(folder, model)
    for image in model.sorted_images():
        sparse = load_prior_maps(folder, "sfm", image.name).depth
        median = float(np.median(sparse[sparse > 0]))
        dense = np.full(sparse.shape, median, np.float32)
        write_prior_maps(folder, "labels", image.name, depth=dense, normal=np.dstack([0 * dense, 0 * dense, 1 + 0 * dense]),
                         mask=np.ones(sparse.shape, bool))
        write_prior_maps(folder, "ndn", image.name, depth=dense, normal=np.dstack([0 * dense, 0 * dense, 1 + 0 * dense]),
                         mask=np.ones(sparse.shape, bool), relative_depth=True, mask_kind="surface")
    return folder


def test_the_folder_is_written_read_back_cached_and_rebuilt_when_its_inputs_change(scene, monkeypatch):
    computed = []
    monkeypatch.setattr(auto, "_compute_source", lambda s, source, p: computed.append(str(source)))
    first = ensure_auto_priors(scene)
    assert computed == []  # every source was there
    folder = SceneDir(scene)
    name = read_model(scene).sorted_images()[0].name
    maps = load_prior_maps(scene, PriorSource.AUTO, name)
    assert maps.confidence is not None and maps.confidence.shape == maps.mask.shape
    assert maps.sky is not None and not maps.sky.any()  # ndn's mask marks no sky here
    assert not maps.relative_depth and maps.normal is not None
    half = load_prior_maps(scene, PriorSource.AUTO, name, size=(maps.mask.shape[1] // 2, maps.mask.shape[0] // 2))
    assert half.confidence.shape == half.mask.shape == (maps.mask.shape[0] // 2, maps.mask.shape[1] // 2)
    report = json.loads((folder.prior(PriorSource.AUTO) / auto.REPORT_NAME).read_text())
    assert report["sources_used"] == ["sfm", "labels", "ndn"] and report["summary"]["views"] == 8

    stamp = (folder.prior(PriorSource.AUTO) / auto.REPORT_NAME).stat().st_mtime_ns
    assert ensure_auto_priors(scene)["inputs"] == first["inputs"]
    assert (folder.prior(PriorSource.AUTO) / auto.REPORT_NAME).stat().st_mtime_ns == stamp  # reused, not rebuilt

    # a source recomputed by hand: fused again, nothing recomputed
    sparse = load_prior_maps(scene, "labels", name)
    write_prior_maps(scene, "labels", name, depth=sparse.depth * 1.01, normal=sparse.normal, mask=sparse.mask)
    ensure_auto_priors(scene)
    assert computed == [] and (folder.prior(PriorSource.AUTO) / auto.REPORT_NAME).stat().st_mtime_ns != stamp

    # new images: every source is recomputed before the fusion
    (folder.images / name).write_bytes(b"a different photo")
    ensure_auto_priors(scene)
    assert computed == ["sfm", "labels", "ndn"]


def test_a_source_that_cannot_be_computed_is_left_out_and_said(scene, monkeypatch):
    import shutil

    shutil.rmtree(SceneDir(scene).prior("labels"))
    messages = []
    monkeypatch.setattr(auto, "_compute_source", lambda s, source, p: "no bpy here" if source == "labels" else None)
    report = ensure_auto_priors(scene, lambda event: messages.append(event.message))
    assert report["sources_used"] == ["sfm", "ndn"] and report["skipped"] == {"labels": "no bpy here"}
    assert any("labels left out: no bpy here" in m for m in messages)
    assert any(m.startswith("auto priors: ") and "% of pixels" in m for m in messages)


def test_no_staging_folder_is_left_when_the_fusion_fails(scene, monkeypatch):
    monkeypatch.setattr(auto, "_compute_source", lambda *a: None)
    monkeypatch.setattr(auto, "fuse_view", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("boom")))
    with pytest.raises(RuntimeError):
        ensure_auto_priors(scene)
    priors = SceneDir(scene).priors
    assert sorted(p.name for p in priors.iterdir()) == ["labels", "ndn", "sfm"]


# --- the losses -------------------------------------------------------------------------
def test_confidence_scales_each_pixel_of_both_losses_without_renormalising():
    torch.manual_seed(0)
    prior = torch.full((8, 8), 4.0)
    rendered = (prior * (1 + 0.1 * torch.rand(8, 8))).requires_grad_()
    mask = torch.ones(8, 8, dtype=torch.bool)
    full = depth_loss(rendered, prior, mask).detach()
    half = depth_loss(rendered, prior, mask, confidence=torch.full((8, 8), 0.5)).detach()
    assert float(half) == pytest.approx(0.5 * float(full), rel=1e-6)
    left = torch.zeros(8, 8)
    left[:, :4] = 1.0
    only_left = depth_loss(rendered, prior, mask, confidence=left)
    expected = (torch.log(rendered) - torch.log(prior)).abs()[:, :4].sum() / 64
    assert float(only_left.detach()) == pytest.approx(float(expected.detach()), rel=1e-5)
    only_left.backward()
    assert (rendered.grad[:, 4:] == 0).all() and (rendered.grad[:, :4] != 0).all()

    normals = torch.nn.functional.normalize(torch.rand(8, 8, 3), dim=-1)
    target = torch.zeros(8, 8, 3)
    target[..., 2] = 1.0
    full = normal_loss(normals, target, mask)
    assert float(normal_loss(normals, target, mask, confidence=torch.full((8, 8), 0.25))) == pytest.approx(
        0.25 * float(full), rel=1e-6)


# --- before training ----------------------------------------------------------------------
def test_training_on_auto_makes_the_priors_first_and_its_events_reach_the_run_folder(scene, tmp_path, monkeypatch):
    from esgs.core.formats.run_dir import RunDir
    from esgs.core.methods import esgs_config, prepare_priors
    from esgs.core.progress import ProgressEvent
    from esgs.core.train.config import TrainConfig

    calls = []

    def fake(scene_dir, progress):
        calls.append(scene_dir)
        progress(ProgressEvent(0, 0, "auto priors", kind="message", message="auto priors: computing labels"))
        return {"summary": {}}

    monkeypatch.setattr(auto, "ensure_auto_priors", fake)
    out = tmp_path / "run"
    assert prepare_priors(esgs_config(scene, out)) == {"summary": {}} and calls == [scene]
    lines = [json.loads(line) for line in RunDir(out).events.read_text().splitlines()]
    assert lines[-1]["message"] == "auto priors: computing labels"
    # plain 3DGS and ESGS on another source make nothing; a given callback gets the events instead
    assert prepare_priors(TrainConfig(scene=scene, out=tmp_path / "plain")) is None
    assert prepare_priors(esgs_config(scene, tmp_path / "ndn", priors="ndn")) is None
    seen = []
    prepare_priors(esgs_config(scene, tmp_path / "given"), seen.append)
    assert [e.message for e in seen] == ["auto priors: computing labels"] and not (tmp_path / "given").exists()
    assert len(calls) == 2
