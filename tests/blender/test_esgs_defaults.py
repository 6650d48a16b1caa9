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
