"""Where a user starts ESGS, it is the same method on the same priors (issue 23): the Blender
panel's Training section and the demo both build full ESGS through
:func:`esgs.core.methods.full_esgs` on ``auto`` priors, and the panel's *Compute Priors* and the
demo's priors stage both run the priors job (:func:`esgs.core.priors.job.compute_priors`) for
``auto``."""
from __future__ import annotations

import inspect

import pytest

bpy = pytest.importorskip("bpy")

from esgs.core import methods  # noqa: E402
from esgs.core.apps import demo, jobs  # noqa: E402
from esgs.core.config import config_from_dict  # noqa: E402
from esgs.core.errors import ESGSError  # noqa: E402
from esgs.core.priors import job as priors_job_core  # noqa: E402
from esgs.esgs_addon import settings_training, training_job  # noqa: E402
from tests.blender.test_interrupted_jobs import save_and_reopen  # noqa: E402


def test_the_panel_and_the_demo_build_esgs_with_the_same_function(monkeypatch):
    real = methods.full_esgs
    calls = []

    def spy(priors="auto", **kwargs):
        calls.append(priors)
        return real(priors, **kwargs)

    monkeypatch.setattr(methods, "full_esgs", spy)
    settings = bpy.context.scene.esgs.training
    settings.method = "esgs"  # what a user does in the panel: the rest is its default
    panel = training_job.training_config(settings)
    assert calls and set(calls) == {"auto"}  # the panel filled its settings in with full_esgs("auto")

    calls.clear()
    config = demo.DemoConfig()
    demo_settings = config_from_dict(methods.ESGSConfig, demo.esgs_settings(config.priors, config.gpdfn))
    assert calls == ["auto"]

    assert panel.method == "esgs" and panel.method_config == demo_settings == real()
    assert demo_settings.depth_weight == methods.AUTO_DEPTH_WEIGHT  # auto's weight reaches both, not ndn's
    assert panel.method_config.prior_points == demo_settings.prior_points == methods.AUTO_PRIOR_POINTS > 0
    # one default source: full_esgs's, the demo's and the panel's
    default = inspect.signature(real).parameters["priors"].default
    assert default == config.priors == settings_training.DEFAULT_PRIOR_SOURCE == "auto"


def test_compute_priors_in_the_panel_and_the_demo_request_auto(tmp_path, monkeypatch):
    from tests.blender.colmap_helpers import synthetic_model, write_scene

    scene = write_scene(tmp_path, synthetic_model(), name="scene")
    assert bpy.context.scene.esgs.priors.method == "auto"  # the panel's default
    started = []

    def start_job(key, job, **kwargs):
        started.append(job)
        raise ESGSError("not started in this test")

    monkeypatch.setattr(jobs, "start_job", start_job)
    bpy.context.scene.esgs.training.scene_dir = str(scene)
    with pytest.raises(RuntimeError, match="not started in this test"):
        bpy.ops.esgs.compute_priors()
    (job,) = started
    job.cleanup()
    assert (job.job, job.config.method, job.config.scene) == ("priors", "auto", scene)
    assert isinstance(job.config, priors_job_core.PriorsSettings)  # what the child hands to compute_priors

    requested = []

    def compute(settings, progress):
        requested.append(settings)
        raise ESGSError("stop here")

    monkeypatch.setattr(priors_job_core, "compute_priors", compute)
    with pytest.raises(ESGSError, match="stop here"):
        demo.make_priors(demo.DemoConfig(out=tmp_path), scene, lambda event: None)
    assert requested == [job.config]  # the same request as the panel's


def test_a_full_esgs_saved_before_an_option_existed_gets_it_when_the_file_is_opened(tmp_path, capsys):
    settings = bpy.context.scene.esgs.training
    settings.method = "esgs"  # the panel fills in full ESGS on auto
    assert settings.prior_points == methods.AUTO_PRIOR_POINTS
    settings.property_unset("prior_points")  # as a file saved before prior_points existed stores it
    assert settings.prior_points == methods.ESGSConfig.prior_points == 0

    save_and_reopen(tmp_path / "old.blend")

    settings = bpy.context.scene.esgs.training
    assert settings.prior_points == methods.AUTO_PRIOR_POINTS
    assert training_job.training_config(settings).method_config == methods.full_esgs("auto")
    assert f"prior_points = {methods.AUTO_PRIOR_POINTS}" in capsys.readouterr().out


def test_settings_the_user_chose_are_kept_when_the_file_is_opened(tmp_path):
    settings = bpy.context.scene.esgs.training
    settings.method = "esgs"
    settings.prior_points = 0  # set by hand: stored, even at its default
    save_and_reopen(tmp_path / "chosen.blend")
    assert bpy.context.scene.esgs.training.prior_points == 0
    assert settings_training.complete_saved_full_esgs(bpy.context.scene.esgs.training) == []

    # an option added since is not filled in where another stored option is the user's own
    settings = bpy.context.scene.esgs.training
    settings.prior_points = methods.AUTO_PRIOR_POINTS
    settings.property_unset("prior_points")
    settings.depth_weight = 2.5 * methods.AUTO_DEPTH_WEIGHT
    save_and_reopen(tmp_path / "own.blend")
    settings = bpy.context.scene.esgs.training
    assert settings.prior_points == 0 and settings.depth_weight == pytest.approx(2.5 * methods.AUTO_DEPTH_WEIGHT)

    # nor where the file trains 3DGS
    settings.method = "3dgs"
    settings.depth_weight = methods.AUTO_DEPTH_WEIGHT
    assert settings_training.complete_saved_full_esgs(settings) == []
    assert settings.prior_points == 0
