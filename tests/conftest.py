"""Shared fixtures: where the real data lives, and the CI rule for it.

Tests that need ``../shared/data`` use the ``shared_data`` fixture. On a user's clone
without it they skip with a reason; with ``CI=true`` a missing dataset is a failure.
"""
from __future__ import annotations

import contextlib
import importlib.util
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before anything imports torch

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_data_root() -> Path:
    """``$ESGS_SHARED_DATA`` or ``<repo>/../shared/data``."""
    env = os.environ.get("ESGS_SHARED_DATA")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data"


def require_shared(*parts: str) -> Path:
    """Path to a shared dataset; skip (or fail under CI=true) when it is absent."""
    path = shared_data_root().joinpath(*parts)
    if not path.exists():
        message = f"shared data not found: {path} (set ESGS_SHARED_DATA)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + " - CI must have it")
        pytest.skip(message)
    return path


@pytest.fixture
def shared_data() -> Path:
    return require_shared()


@contextlib.contextmanager
def benchmark_script(name: str):
    """The module of ``benchmarks/<name>.py`` (a script, not a package: loaded from its path),
    registered in ``sys.modules`` while in use (its dataclasses look their module up there)."""
    path = REPO_ROOT / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)
