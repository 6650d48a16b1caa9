"""``core`` must import in a Python where bpy (and the Blender-side packages) cannot be imported."""
from __future__ import annotations

import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import importlib, importlib.abc, pkgutil, sys

    BLOCKED = ("bpy", "bpy_extras", "mathutils", "esgs.esgs_addon", "esgs.operators", "esgs.panels")

    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if any(name == b or name.startswith(b + ".") for b in BLOCKED):
                raise ImportError(f"blocked for this test: {name}")
            return None

    sys.meta_path.insert(0, Block())
    import esgs, esgs.core
    failures = []
    count = 0
    for info in pkgutil.walk_packages(esgs.core.__path__, "esgs.core."):
        if info.name.endswith("__main__"):
            continue
        try:
            importlib.import_module(info.name)
            count += 1
        except ImportError as err:
            if "blocked for this test" in str(err):
                failures.append(f"{info.name}: {err}")
            else:
                raise
    assert not failures, failures
    assert not any(m == "bpy" or m.startswith("bpy.") for m in sys.modules)
    print("imported", count)
    """
)


def test_every_core_module_imports_without_bpy():
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    count = int(result.stdout.split()[-1])
    assert count >= 5


def test_core_sources_never_mention_blender_imports():
    from pathlib import Path

    import esgs.core

    root = Path(esgs.core.__file__).parent
    offenders = []
    for path in root.rglob("*.py"):
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            stripped = line.strip()
            if stripped.startswith(("import bpy", "from bpy", "import mathutils", "from mathutils")) or (
                stripped.startswith("from ..") and any(p in stripped for p in ("esgs_addon", "operators", "panels"))
            ):
                offenders.append(f"{path.relative_to(root)}:{number}: {stripped}")
    assert not offenders, offenders
