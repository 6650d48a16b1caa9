"""The repository root *is* the package ``esgs`` (it is also the Blender extension).

setuptools cannot express "map the root folder to a package and discover its
subpackages" in pyproject.toml alone, so this file does only that.
"""
from setuptools import find_packages, setup

_SUBPACKAGE_ROOTS = ("core", "esgs_addon", "operators", "panels")
_subpackages = [
    p for p in find_packages(where=".") if p.split(".")[0] in _SUBPACKAGE_ROOTS
]

setup(
    packages=["esgs"] + [f"esgs.{p}" for p in _subpackages],
    package_dir={"esgs": "."},
    package_data={"esgs": ["blender_manifest.toml"], "esgs.core": ["presets/*.toml", "data/*"],
                  "esgs.core.terrain": ["presets/*.toml"], "esgs.core.ndn": ["weights/*.pt"]},
)
