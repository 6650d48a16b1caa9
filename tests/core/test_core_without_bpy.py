"""``core`` must import in a Python where bpy (and the Blender-side packages) cannot be imported."""
from __future__ import annotations

import ast
import os
import subprocess
import sys
import textwrap
from pathlib import Path

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
    import os
    import cv2  # its own loader adds to LD_LIBRARY_PATH: a third party's doing, before we look
    environment = dict(os.environ)
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
    changed = sorted(set(environment.items()) ^ set(os.environ.items()))
    assert not changed, f"importing the engine changed the environment: {changed}"
    print("imported", count)
    """
)


def _environment_without_thread_settings() -> dict[str, str]:
    """This process's environment less what tests/conftest.py and a CLI would set, so a module
    that sets one of them on import is caught."""
    return {k: v for k, v in os.environ.items() if k not in _THREAD_VARIABLES}


_THREAD_VARIABLES = ("OMP_WAIT_POLICY", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "ESGS_THREADS")

IMPORT_ONLY = textwrap.dedent(
    """
    import os, sys
    before = dict(os.environ)
    import torch
    threads = torch.get_num_threads()
    import esgs, esgs.core, esgs.core.cli, esgs.core.render, esgs.core.train, esgs.core.train.trainer
    changed = sorted(set(before.items()) ^ set(os.environ.items()))
    assert not changed, f"importing the engine changed the environment: {changed}"
    assert torch.get_num_threads() == threads, "importing the engine changed torch's thread count"
    print("unchanged")
    """
)


def test_importing_the_engine_changes_nothing_global():
    """No environment variable (OMP_WAIT_POLICY included) and no thread count changes on import:
    the process may be Blender's. The CLI's main() and the runtime's children set them."""
    result = subprocess.run([sys.executable, "-c", IMPORT_ONLY], capture_output=True, text=True, timeout=600,
                            env=_environment_without_thread_settings())
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.split()[-1] == "unchanged"


def test_every_core_module_imports_without_bpy():
    result = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=600,
                            env=_environment_without_thread_settings())
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


def test_every_child_entry_point_resolves_to_a_module():
    """The registry names modules that exist (found without importing them, so no bpy)."""
    import importlib.util

    from esgs.core.runtime.entry_points import CHILD_MODULE, ENTRY_POINTS

    assert {"train", "priors", "labels", "scene", "render_labels", "results_scene"} <= set(ENTRY_POINTS)
    assert importlib.util.find_spec(CHILD_MODULE) is not None
    for name, entry in ENTRY_POINTS.items():
        module = entry.absolute_module
        assert importlib.util.find_spec(module) is not None, f"{name}: {module} not found"
        if not entry.needs_bpy:  # the others import bpy: read their source instead
            assert callable(getattr(importlib.import_module(module), entry.function)), name
        source = Path(importlib.util.find_spec(module).origin).read_text(encoding="utf-8")
        assert f"def {entry.function}(" in source, f"{name}: no {entry.function} in {module}"


def _code_strings(tree: ast.AST) -> list[tuple[int, str]]:
    """String constants of a module that are not docstrings, with their line numbers."""
    docstrings = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                docstrings.add(id(body[0].value))
    return [(node.lineno, node.value) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings]


def test_no_core_module_names_a_child_module_by_hand():
    """Only the runtime's registry names add-on modules or our own ``-m`` command lines, so
    the test above covers every child a core module starts."""
    core = Path(__file__).resolve().parents[2] / "core"
    runtime = core / "runtime"
    offenders = []
    for path in sorted(core.rglob("*.py")):
        if runtime in path.parents:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for line, text in _code_strings(tree):
            if "esgs.esgs_addon" in text or "esgs_addon." in text:
                offenders.append(f"{path.relative_to(core)}:{line}: {text!r}")
        for node in ast.walk(tree):
            if isinstance(node, (ast.List, ast.Tuple)):
                items = [e.value if isinstance(e, ast.Constant) else None for e in node.elts]
                for first, second in zip(items, items[1:]):
                    if first == "-m" and isinstance(second, str) and second.startswith("esgs"):
                        offenders.append(f"{path.relative_to(core)}:{node.lineno}: -m {second}")
    assert not offenders, offenders
