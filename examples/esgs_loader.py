"""What every example script needs before it can use ESGS: the package and its own arguments.

The examples run three ways: ``python examples/X.py ARGS`` with the ``bpy`` module in this
checkout's ``.venv`` (the package is installed there, editable), ``blender -b --python
examples/X.py -- ARGS`` with the ESGS extension enabled in Blender, or either of those from a
plain checkout where nothing is installed. A script finds this module beside itself::

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from esgs_loader import load_esgs, script_arguments

(Blender's ``--python`` does not put the script's folder on ``sys.path``, hence the insert.)
"""
from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

#: The repository root is the package (the Blender extension's folder).
CHECKOUT = Path(__file__).resolve().parents[1]


def load_esgs() -> ModuleType:
    """The ``esgs`` package: installed (pip, editable), enabled as a Blender extension, or this checkout.

    Submodules are then ``importlib.import_module(f"{esgs.__name__}.core.config")``: under
    Blender an extension's package is named ``bl_ext.<repository>.esgs``, not ``esgs``.
    """
    try:
        return importlib.import_module("esgs")
    except ImportError:
        pass
    if "bpy" in sys.modules or _bpy_importable():
        import bpy

        for name in bpy.context.preferences.addons.keys():
            if name.split(".")[-1] == "esgs":
                return importlib.import_module(name)
    # a plain checkout: load the repository root as the package ``esgs``
    spec = importlib.util.spec_from_file_location("esgs", CHECKOUT / "__init__.py",
                                                  submodule_search_locations=[str(CHECKOUT)])
    module = importlib.util.module_from_spec(spec)
    sys.modules["esgs"] = module
    spec.loader.exec_module(module)
    return module


def esgs_module(esgs: ModuleType, name: str) -> ModuleType:
    """A submodule of the loaded package, e.g. ``esgs_module(esgs, "core.errors")``."""
    return importlib.import_module(f"{esgs.__name__}.{name}")


def script_arguments(argv: list[str] | None = None) -> list[str]:
    """The script's own arguments: those after ``--`` (Blender), else everything after the script.

    Under ``blender -b --python X.py`` without ``--``, Blender's own arguments are not the
    script's, so the answer is empty.
    """
    argv = sys.argv if argv is None else argv
    if "--" in argv:
        return argv[argv.index("--") + 1:]
    if argv and Path(argv[0]).name.lower().startswith("blender"):
        return []
    return argv[1:]


def _bpy_importable() -> bool:
    return importlib.util.find_spec("bpy") is not None
