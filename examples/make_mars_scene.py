"""Generate, render and export a synthetic Mars scene folder, headless.

Inside Blender (5.0)::

    blender -b --python examples/make_mars_scene.py -- --preset cratered_plain --seed 3 \\
        --views 30 --resolution 480x270 --out scenes/plain_s3

With the ``bpy`` module (pip install bpy==5.0.1)::

    python examples/make_mars_scene.py --preset rover_horizon --views 12 --out scenes/horizon

Options are those of ``esgs scene`` (run with ``--help``); add ``--sfm`` to also run
pycolmap SfM on the renders, ``--save-blend FILE`` to keep the generated .blend.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path


def import_esgs():
    """Import the ``esgs`` package: installed (pip / Blender extension) or from this checkout."""
    try:
        import esgs  # noqa: F401

        return
    except ImportError:
        pass
    root = Path(__file__).resolve().parents[1]  # the repository root is the package
    spec = importlib.util.spec_from_file_location("esgs", root / "__init__.py", submodule_search_locations=[str(root)])
    module = importlib.util.module_from_spec(spec)
    sys.modules["esgs"] = module
    spec.loader.exec_module(module)


def script_arguments() -> list[str]:
    """Blender passes the script's own arguments after ``--``; plain Python after the script."""
    if "--" in sys.argv:
        return sys.argv[sys.argv.index("--") + 1:]
    return sys.argv[1:]


if __name__ == "__main__":
    import_esgs()
    from esgs.esgs_addon.make_scene import main

    sys.exit(main(script_arguments()))
