"""``esgs info``: versions of the engine and its dependencies, and the compute backends."""
from __future__ import annotations

import argparse
import importlib
import platform

HELP = "print versions of the engine, its dependencies and the available backends"

_PACKAGES = ("numpy", "torch", "pycolmap", "OpenEXR", "cv2", "trimesh", "numba", "scipy", "bpy", "gsplat")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print machine-readable JSON")


def collect() -> dict[str, str]:
    """Versions of the engine's packages ("missing" when not importable)."""
    from ... import __version__

    info = {"esgs": __version__, "python": platform.python_version(), "machine": platform.machine()}
    for name in _PACKAGES:
        if name == "bpy":
            # importing bpy is slow and has side effects; only report whether it is installed
            info[name] = "installed" if importlib.util.find_spec("bpy") else "missing"
            continue
        try:
            module = importlib.import_module(name)
            info[name] = str(getattr(module, "__version__", "installed"))
        except Exception:  # noqa: BLE001 - any import failure means "missing" here
            info[name] = "missing"
    try:
        import torch

        info["cuda"] = "available" if torch.cuda.is_available() else "not available"
    except Exception:  # noqa: BLE001
        info["cuda"] = "not available"
    return info


def run(args: argparse.Namespace) -> int:
    import json

    info = collect()
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        width = max(len(k) for k in info)
        for key, value in info.items():
            print(f"{key:<{width}}  {value}")
    return 0
