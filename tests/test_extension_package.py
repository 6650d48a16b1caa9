"""The extension builds with Blender's own tool and carries exactly the add-on side."""
from __future__ import annotations

import tomllib
import zipfile
from pathlib import Path

import pytest

from esgs.core.apps import packaging

pytest.importorskip("bpy", reason="Blender's extension tool ships with the bpy module")


def test_manifest_passes_blenders_validator():
    packaging.run_blender_ext("validate", str(packaging.REPO_ROOT))  # raises on any problem
    manifest = packaging.read_manifest()
    assert manifest["id"] == "esgs"
    assert manifest["schema_version"] == "1.0.0"
    assert manifest["blender_version_min"] == "5.0.0"
    assert manifest["license"] == ["SPDX:GPL-3.0-or-later"]


def test_manifest_wheels_are_cp311_or_pure_and_never_numpy():
    wheels = packaging.manifest_wheels(packaging.read_manifest())
    assert wheels, "the add-on side needs bundled wheels"
    for wheel in wheels:
        parts = wheel.parts
        assert parts["name"].lower() != "numpy", "Blender ships numpy; never bundle it"
        assert parts["python"] in ("cp311", "py3", "cp37"), wheel.filename  # cp37-abi3 runs on 3.11
        assert parts["name"].lower() not in ("torch", "numba"), "the engine runs in a separate Python"
    for platform in ("linux-x64", "windows-x64", "macos-arm64"):
        names = {w.parts["name"].lower() for w in wheels if w.for_platform(platform)}
        assert {"pycolmap", "openexr", "trimesh"} <= names, (platform, names)


def test_build_linux_package(tmp_path):
    zips = packaging.build_extension(tmp_path, platform="linux-x64")
    assert len(zips) == 1
    with zipfile.ZipFile(zips[0]) as archive:
        names = set(archive.namelist())
        manifest = tomllib.loads(archive.read("blender_manifest.toml").decode())
    assert "__init__.py" in names
    assert any(n.startswith("core/") for n in names)
    assert any(n.startswith("esgs_addon/") for n in names)
    assert "panels/main.py" in names
    # the NDN prior works out of the box: the depth network and the normals network
    assert {"core/ndn/weights/ndn_mars.pt", "core/ndn/weights/ndn_completion.pt"} <= names
    # Preferences > Set Up Trainer installs the trainer from the extension's own files
    assert {"requirements-trainer.txt", "esgs_addon/trainer_setup.py", "operators/trainer_setup.py"} <= names
    with zipfile.ZipFile(zips[0]) as archive:
        shipped = archive.read("requirements-trainer.txt").decode()
    assert shipped == (packaging.REPO_ROOT / packaging.TRAINER_REQUIREMENTS).read_text()
    assert "torch==" in shipped and "\nbpy" not in shipped
    wheel_files = sorted(n for n in names if n.startswith("wheels/"))
    assert wheel_files and all(("manylinux" in n or n.endswith("-any.whl")) for n in wheel_files), wheel_files
    assert manifest["platforms"] == ["linux-x64"]
    assert sorted("wheels/" + Path(w).name for w in manifest["wheels"]) == wheel_files
    # The engine's development files stay out of the add-on.
    for forbidden in ("tests/", ".venv/", "benchmarks/", ".git/", "setup.py", "Makefile"):
        assert not any(n.startswith(forbidden) for n in names), forbidden


def test_narrowing_keeps_only_that_platforms_wheels():
    manifest_text = (packaging.REPO_ROOT / "blender_manifest.toml").read_text()
    wheels = packaging.manifest_wheels(packaging.read_manifest())
    narrowed = tomllib.loads(packaging._narrow_manifest(manifest_text, "windows-x64", wheels))
    assert narrowed["platforms"] == ["windows-x64"]
    assert all(("win_amd64" in w or w.endswith("-any.whl")) for w in narrowed["wheels"])
    assert len(narrowed["wheels"]) == sum(w.for_platform("windows-x64") for w in wheels)


def test_unknown_platform_is_a_clear_error(tmp_path):
    from esgs.core.errors import ConfigError

    with pytest.raises(ConfigError, match="unknown platform"):
        packaging.build_extension(tmp_path, platform="amiga-68k")
