"""One version number: pyproject.toml, blender_manifest.toml and ``esgs.__version__`` agree.

Each is read where its reader reads it (pip from pyproject, Blender from the manifest, the panel
and ``esgs --version`` from the package), so the three copies are kept equal here.
"""
from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

import esgs

ROOT = Path(__file__).resolve().parents[1]


def test_pyproject_manifest_and_package_versions_agree():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text())["version"]
    assert pyproject == manifest == esgs.__version__, (
        f"pyproject.toml {pyproject}, blender_manifest.toml {manifest}, esgs.__version__ {esgs.__version__}: "
        "bump all three together")
    # Blender's manifest wants a semantic version
    assert re.fullmatch(r"\d+\.\d+\.\d+", manifest)


def test_cli_version_is_the_package_version(capsys):
    from esgs.core.cli import main

    with pytest.raises(SystemExit) as raised:
        main(["--version"])
    assert raised.value.code == 0
    assert capsys.readouterr().out.strip() == f"esgs {esgs.__version__}"
