"""Prior maps from Blender (esgs_addon/priors_job.py, operators/priors.py, the training panel).

Headless (the bpy module, like ``blender -b``) the operator blocks until the child
``esgs priors`` process ends; the UI path (a timer) is driven by hand. Every test runs the
real command: SfM priors on a synthetic COLMAP model, NDN priors with a tiny network.
"""
from __future__ import annotations

import shutil

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from esgs.core.apps import jobs  # noqa: E402
from esgs.core.colmap import read_model  # noqa: E402
from esgs.core.priors import load_prior_maps  # noqa: E402
from esgs.core.priors.sfm import sparse_depth_map  # noqa: E402
from esgs.esgs_addon import priors_job  # noqa: E402
from tests.blender.colmap_helpers import synthetic_model, write_scene  # noqa: E402


def _files(folder):
    return {p.relative_to(folder): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.fixture
def sfm_scene(tmp_path):
    """8 views of a bumpy ground patch; SfM priors need only the model."""
    return write_scene(tmp_path, synthetic_model())


@pytest.fixture
def ndn_scene(tmp_path):
    """4 textured 48x27 views with ground-truth priors, and the weights of a ~40k-parameter NDN."""
    torch = pytest.importorskip("torch")
    from esgs.core.ndn.train import build_model, save_checkpoint
    from tests.core.ndn.conftest import make_scene, tiny_config

    scene = make_scene(tmp_path / "scene")
    torch.manual_seed(0)
    model, _ = build_model(tiny_config())
    for parameter in model.parameters():
        parameter.data.add_(0.02 * torch.randn_like(parameter))
    weights = save_checkpoint(tmp_path / "weights.pt", model, tiny_config())
    return scene, weights


def test_operators_are_registered_and_need_a_scene_folder(sfm_scene):
    assert hasattr(bpy.types, "ESGS_OT_compute_priors") and hasattr(bpy.types, "ESGS_OT_compute_priors_cancel")
    assert not bpy.ops.esgs.compute_priors.poll()  # nothing imported, no folder set
    bpy.context.scene.esgs.training.scene_dir = str(sfm_scene.parent / "missing")
    assert not bpy.ops.esgs.compute_priors.poll()
    bpy.context.scene.esgs.training.scene_dir = str(sfm_scene)
    assert bpy.ops.esgs.compute_priors.poll()


def test_headless_operator_writes_sfm_priors(sfm_scene, monkeypatch):
    assert bpy.app.background  # the blocking path is the one under test
    started = []
    monkeypatch.setattr(jobs, "start_job", lambda key, job, **kw: started.append(job) or job.start())
    bpy.context.scene.esgs.training.scene_dir = str(sfm_scene)
    settings = bpy.context.scene.esgs.priors
    settings.method = "sfm"

    assert bpy.ops.esgs.compute_priors() == {"FINISHED"}
    assert settings.status == "finished" and (settings.step, settings.total) == (8, 8)
    assert settings.last_scene_dir == str(sfm_scene) and settings.last_method == "sfm"
    model = read_model(sfm_scene)
    names = sorted(image.name for image in model.images.values())
    assert sorted(p.name for p in (sfm_scene / "priors" / "sfm" / "depth").iterdir()) == [
        n.replace(".png", ".exr") for n in names]
    assert sorted(p.name for p in (sfm_scene / "priors" / "sfm" / "mask").iterdir()) == names
    for image in model.sorted_images()[:2]:
        maps = load_prior_maps(sfm_scene, "sfm", image.name)
        np.testing.assert_array_equal(maps.depth, sparse_depth_map(model, image.image_id))
        assert maps.mask.sum() == np.count_nonzero(maps.depth) > 0
    assert [p.name for p in (sfm_scene / "priors").iterdir()] == ["sfm"]  # no staging folder left
    assert not started[0].events_path.parent.exists()  # the temporary events folder is gone


def test_headless_operator_writes_ndn_priors_like_the_library_call(ndn_scene, tmp_path):
    from esgs.core.ndn.infer import write_ndn_priors

    scene, weights = ndn_scene
    gt_before = _files(scene / "priors" / "gt")
    bpy.context.scene.esgs.training.scene_dir = str(scene)
    settings = bpy.context.scene.esgs.priors
    settings.method = "ndn"
    settings.ndn_weights = str(weights)

    assert bpy.ops.esgs.compute_priors() == {"FINISHED"}, settings.error
    assert settings.status == "finished" and settings.total == 4
    assert sorted(p.name for p in (scene / "priors").iterdir()) == ["gt", "ndn"]
    for kind, extension in (("depth", "exr"), ("normal", "exr"), ("mask", "png")):
        assert sorted(p.name for p in (scene / "priors" / "ndn" / kind).iterdir()) == [
            f"view_{i:03d}.{extension}" for i in range(4)]
    assert _files(scene / "priors" / "gt") == gt_before
    # the child computed what the library computes in this process (same weights, seed 0)
    reference = tmp_path / "reference"
    shutil.copytree(scene / "images", reference / "images")
    shutil.copytree(scene / "sparse", reference / "sparse")
    write_ndn_priors(reference, weights)
    for index in (0, 3):
        name = f"view_{index:03d}.png"
        ours, theirs = load_prior_maps(scene, "ndn", name), load_prior_maps(reference, "ndn", name)
        assert ours.relative_depth and ours.depth.shape == (27, 48) and ours.mask.any()
        np.testing.assert_allclose(ours.depth, theirs.depth, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(ours.normal, theirs.normal, atol=1e-5)
        np.testing.assert_array_equal(ours.mask, theirs.mask)


def test_errors_are_reported_and_leave_nothing_behind(ndn_scene, tmp_path):
    scene, weights = ndn_scene
    before = _files(scene)
    settings = bpy.context.scene.esgs.priors
    training = bpy.context.scene.esgs.training

    with pytest.raises(RuntimeError, match="Render Dataset, Import COLMAP or choose"):  # poll says why
        bpy.ops.esgs.compute_priors()

    empty = tmp_path / "empty"
    (empty / "images").mkdir(parents=True)
    training.scene_dir = str(empty)
    with pytest.raises(RuntimeError, match="no COLMAP model found"):
        bpy.ops.esgs.compute_priors()
    assert [p.name for p in empty.iterdir()] == ["images"]

    training.scene_dir = str(scene)
    settings.method = "ndn"
    settings.ndn_weights = str(tmp_path / "no_such_weights.pt")
    with pytest.raises(RuntimeError, match="NDN weights not found"):
        bpy.ops.esgs.compute_priors()

    # a file that exists but is no checkpoint: the child fails; its message reaches Blender
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    settings.ndn_weights = str(tmp_path / "bad.pt")
    with pytest.raises(RuntimeError, match="cannot read NDN weights"):
        bpy.ops.esgs.compute_priors()
    assert settings.status == "failed" and "bad.pt" in settings.error
    assert _files(scene) == before and sorted(p.name for p in (scene / "priors").iterdir()) == ["gt"]


def test_ui_polling_follows_the_job_and_cleans_up(sfm_scene, monkeypatch):
    """The timer path of the UI, driven by hand (timers never fire in background mode)."""
    from esgs.panels.training_panel import ESGS_PT_training
    from tests.blender.test_training_operator import draw_panel

    registered = []
    monkeypatch.setattr(bpy.app.timers, "register", lambda function, **kwargs: registered.append(function))
    bpy.context.scene.esgs.training.scene_dir = str(sfm_scene)
    settings = bpy.context.scene.esgs.priors
    record = draw_panel(ESGS_PT_training)
    assert ("operator", "esgs.compute_priors") in record and ("prop", "method") in record

    job = priors_job.start_priors(sfm_scene, "sfm")
    priors_job.copy_state(settings, job.state(), scene_dir=sfm_scene, method="sfm")
    assert not bpy.ops.esgs.compute_priors.poll()  # one job per scene folder
    record = draw_panel(ESGS_PT_training)
    assert ("operator", "esgs.compute_priors_cancel") in record
    assert any(kind == "progress" and text.startswith("sfm: ") for kind, text in record)

    priors_job.start_polling(bpy.context.scene.name, priors_job.job_key(sfm_scene))
    (poll,) = registered
    for _ in range(600):
        if poll() is None:
            break
        job.wait(timeout=0.1)
    else:
        pytest.fail("the poller never saw the job end")
    assert settings.status == "finished" and settings.progress == 1.0
    assert not job.events_path.parent.exists()
    assert len(list((sfm_scene / "priors" / "sfm" / "depth").iterdir())) == 8
    record = draw_panel(ESGS_PT_training)
    assert ("label", "Priors written: priors/sfm") in record


def test_cancel_stops_the_child_and_writes_nothing(tmp_path):
    """Cancelled while the network samples (the shipped weights). 96 views, so that after the
    first event there is work left for many seconds even on an idle machine: with 4 the child
    could finish between the first event and the cancel on a loaded one, and with 24 it did once
    while other training runs shared the 2 cores. The cancel stops it at the next view, so the
    extra views cost only their (small) images."""
    from tests.core.ndn.conftest import make_scene

    scene = make_scene(tmp_path / "scene", views=96)
    before = _files(scene)
    job = priors_job.start_priors(scene, "ndn")
    bpy.context.scene.esgs.priors.last_scene_dir = str(scene)
    state = job.state()
    for _ in range(1200):  # the first event comes once torch is loaded and sampling starts
        state = job.state()
        if state.events_seen or not state.active:
            break
        job.wait(timeout=0.05)
    assert state.status == "running" and state.events_seen, state
    assert bpy.ops.esgs.compute_priors_cancel() == {"FINISHED"}
    assert job.state().status == "cancelled"
    assert _files(scene) == before and sorted(p.name for p in (scene / "priors").iterdir()) == ["gt"]
    assert not job.events_path.parent.exists()


def test_default_weights_path_matches_the_engine():
    shipped = pytest.importorskip("esgs.core.ndn.shipped")
    assert priors_job.SHIPPED_NDN_WEIGHTS == shipped.SHIPPED_WEIGHTS
    assert priors_job.SHIPPED_NDN_NORMAL_WEIGHTS == shipped.SHIPPED_NORMAL_WEIGHTS
    assert priors_job.NDN_NORMAL_WEIGHTS_VARIABLE == shipped.NORMAL_WEIGHTS_ENVIRONMENT_VARIABLE
    assert priors_job.default_ndn_weights("x.pt").name == "x.pt"


def test_a_missing_shipped_normals_network_is_refused_before_any_process(ndn_scene, tmp_path, monkeypatch):
    scene, _ = ndn_scene
    monkeypatch.delenv(priors_job.NDN_WEIGHTS_VARIABLE, raising=False)
    monkeypatch.delenv(priors_job.NDN_NORMAL_WEIGHTS_VARIABLE, raising=False)
    priors_job.check_scene(scene, "ndn")  # both shipped networks are there
    monkeypatch.setattr(priors_job, "SHIPPED_NDN_NORMAL_WEIGHTS", tmp_path / "gone.pt")
    with pytest.raises(priors_job.CheckpointError, match="normal weights are missing"):
        priors_job.check_scene(scene, "ndn")
    # a named normals network (or 'same') does not need the shipped one
    monkeypatch.setenv(priors_job.NDN_NORMAL_WEIGHTS_VARIABLE, "same")
    priors_job.check_scene(scene, "ndn")
