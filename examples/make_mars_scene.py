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

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # esgs_loader.py, also under blender --python
from esgs_loader import esgs_module, load_esgs, script_arguments  # noqa: E402


if __name__ == "__main__":
    esgs = load_esgs()
    sys.exit(esgs_module(esgs, "esgs_addon.make_scene").main(script_arguments()))
