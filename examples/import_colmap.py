"""Import a COLMAP scene into Blender headless and save it as a .blend file.

Run either way:

    blender -b --python examples/import_colmap.py -- SCENE [--output scene.blend] [--orient-up] ...
    python examples/import_colmap.py SCENE [--output scene.blend] [--image-planes] ...   (bpy module)

SCENE is a folder holding images/ and sparse/0 (or the COLMAP model folder itself). Every
option of the import (``ColmapImportOptions``) is a flag; ``--help`` lists them.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # esgs_loader.py, also under blender --python
from esgs_loader import esgs_module, load_esgs, script_arguments  # noqa: E402


def main(argv: list[str]) -> int:
    import bpy

    esgs = load_esgs()
    config = esgs_module(esgs, "core.config")
    errors = esgs_module(esgs, "core.errors")
    colmap_scene = esgs_module(esgs, "esgs_addon.colmap_scene")

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path, help="scene folder (images/ + sparse/0) or COLMAP model folder")
    parser.add_argument("--output", type=Path, help="the .blend to write (default: SCENE/<name>.blend)")
    config.add_dataclass_arguments(parser, colmap_scene.ColmapImportOptions)
    args = parser.parse_args(argv)
    options = config.dataclass_from_args(colmap_scene.ColmapImportOptions, args)

    bpy.ops.wm.read_factory_settings(use_empty=True)
    esgs.register()
    try:
        result = colmap_scene.import_colmap_scene(args.scene, options)
    except errors.ESGSError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    for warning in result["warnings"]:
        print(f"warning: {warning}", file=sys.stderr)
    output = args.output or args.scene / f"{result['collection'].name}.blend"
    output = output.resolve()
    output.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(output))
    points = result["points"]
    print(
        f"imported {len(result['cameras'])} cameras and {len(points.data.points) if points else 0} points "
        f"into collection '{result['collection'].name}'; saved {output}"
    )
    return 0


if __name__ == "__main__":
    code = main(script_arguments())
    if code:
        sys.exit(code)
