"""A tiny experiment scene: the training tests' plane with gt priors and a ground-truth mesh."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def make_experiment_scene(root: Path, views: int = 6) -> Path:
    import trimesh

    from tests.core.methods.test_esgs_hooks import _write_gt_priors
    from tests.core.train.scene import make_scene

    scene = make_scene(Path(root), views=views, width=32, height=24)
    _write_gt_priors(scene)
    # the known Gaussians lie on z ~ 0 over [-1, 1]^2: a flat square is their surface
    vertices = np.array([[-1.5, -1.5, 0.0], [1.5, -1.5, 0.0], [1.5, 1.5, 0.0], [-1.5, 1.5, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    (scene / "mesh").mkdir(exist_ok=True)
    trimesh.Trimesh(vertices, faces, process=False).export(scene / "mesh" / "ground_truth.ply")
    return scene


def load_benchmark_script(name: str):
    """The module of ``benchmarks/<name>.py`` (a script, not a package: loaded from its path)."""
    import importlib.util

    path = Path(__file__).resolve().parents[3] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
