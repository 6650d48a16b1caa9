"""The add-on's ``load_post`` handlers (esgs_addon/_registry.py, ``file_load_hooks``): each is
added once when the add-on registers and removed when it unregisters, and runs on file load."""
from __future__ import annotations

import pytest

bpy = pytest.importorskip("bpy")

from esgs.esgs_addon import interrupted_jobs, settings_training  # noqa: E402
from tests.blender.test_interrupted_jobs import save_and_reopen  # noqa: E402


@pytest.mark.parametrize("module", [interrupted_jobs, settings_training], ids=lambda module: module.__name__)
def test_each_handler_is_registered_once_and_removed(module):
    import esgs

    handler = module.on_file_loaded
    assert [h for h in bpy.app.handlers.load_post if h is handler] == [handler]
    module.register_hooks()  # registering again adds nothing
    assert [h for h in bpy.app.handlers.load_post if h is handler] == [handler]
    esgs.unregister()
    try:
        assert handler not in bpy.app.handlers.load_post
    finally:
        esgs.register()
    assert handler in bpy.app.handlers.load_post


def test_the_handlers_run_when_a_file_is_opened(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(interrupted_jobs, "update_saved_job_states", lambda scenes: calls.append("jobs") or [])
    monkeypatch.setattr(settings_training, "complete_saved_full_esgs", lambda group: calls.append("settings") or [])
    save_and_reopen(tmp_path / "a.blend")
    assert sorted(calls) == ["jobs", "settings"]
