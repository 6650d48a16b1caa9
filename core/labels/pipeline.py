"""The whole label job without Blender in this process: reconstruct (optional), render in a
Blender child process, report. What ``esgs labels`` runs; scripts can call it too.

The rendering needs the ``bpy`` module, which ``core`` never imports: it runs the
``"render_labels"`` job of the child-process runtime (:mod:`esgs.core.runtime`) and relays
the child's progress events.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import ConfigError, DatasetError
from ..progress import ProgressCallback, no_progress
from ..runtime import run_job
from .fill import FillOptions
from ..formats.scene_dir import PriorSource, SceneDir
from .reconstruct import ReconstructOptions


@dataclass
class LabelJob:
    """One label run: where, from which mesh, and how."""

    scene: Path
    mesh: Path | None = None
    reconstruct: bool = False
    reconstruct_options: ReconstructOptions = field(default_factory=ReconstructOptions)
    fill: FillOptions = field(default_factory=FillOptions)
    samples: int = 0
    smooth: bool = True
    report: bool = False

    def validate(self) -> None:
        if (self.mesh is None) == (not self.reconstruct):
            raise ConfigError("give exactly one of --mesh MESH and --reconstruct")
        self.reconstruct_options.validate()
        self.fill.validate()
        if self.samples < 0:
            raise ConfigError(f"samples must be >= 0, got {self.samples}")


def check_scene(scene: Path) -> int:
    """Fail early for a scene the renderer could not label; return its number of images."""
    from ..colmap.io import read_model

    if not Path(scene).is_dir():
        raise DatasetError("scene folder not found", path=scene, hint="give a folder with images/ and sparse/0")
    model = read_model(scene)
    if not model.images:
        raise DatasetError("the COLMAP model has no images (no cameras to render)", path=scene,
                           hint="run SfM first (esgs dataset from-images) so every image has a pose")
    check_pinhole(model, scene)
    return len(model.images)


def check_pinhole(model, scene: Path) -> None:
    """Labels are pixel-exact only for cameras without lens distortion (Blender has none)."""
    distorted = sorted({f"{camera.camera_id} ({camera.model})" for camera in model.cameras.values()
                        if not camera.is_pinhole})
    if distorted:
        raise DatasetError(f"cameras with lens distortion: {', '.join(distorted)}; labels rendered by Blender "
                           "would not line up with the images", path=scene,
                           hint="undistort the scene first (esgs colmap undistort), then label the undistorted folder")


def run_label_job(job: LabelJob, progress: ProgressCallback = no_progress, *, verbose: bool = False) -> dict[str, Any]:
    """Reconstruct a mesh if asked, render the labels in a Blender child process, and with
    ``job.report`` compare them with ``priors/gt``. Returns ``{"labels": labels.json dict,
    "reconstruction": dict | None, "accuracy": dict | None}``."""
    import importlib.util

    from ..io_utils import atomic_write_json

    job.validate()
    check_scene(job.scene)
    if job.mesh is not None and not Path(job.mesh).is_file():
        raise DatasetError("mesh file not found", path=job.mesh, hint="give an existing mesh, or use --reconstruct")
    if job.report and not SceneDir(job.scene).has_prior_maps(PriorSource.GT, "depth"):
        raise DatasetError("--report needs the ground truth of a synthetic scene (priors/gt/depth)", path=job.scene)
    if importlib.util.find_spec("bpy") is None:
        raise ConfigError("rendering labels needs Blender's bpy module, which this Python does not have",
                          hint="pip install bpy==5.0.1")
    reconstruction = None
    gaps = None
    metadata: dict[str, str] = {}
    if job.reconstruct:
        from .reconstruct import reconstruct_mesh

        mesh = SceneDir(job.scene).reconstructed_mesh
        reconstruction = reconstruct_mesh(job.scene, job.reconstruct_options, out_path=mesh, progress=progress)
        atomic_write_json(SceneDir(job.scene).reconstruction_report, reconstruction)
        gaps = reconstruction["gaps"]
        metadata = {"reconstruction": "plane-sweep ZNCC stereo, cross-view check, 2.5D Delaunay "
                                      "(esgs.core.labels.reconstruct)",
                    "reconstruction_report": str(SceneDir(job.scene).reconstruction_report.resolve())}
        method = "reconstruct"
    else:
        mesh = Path(job.mesh)
        method = "mesh"
    request = {"scene": str(job.scene), "mesh": str(mesh), "method": method, "samples": job.samples,
               "smooth": job.smooth, "fill": job.fill, "metadata": metadata,
               "gaps": None if gaps is None else str(gaps)}
    run_job("render_labels", request, progress, verbose=verbose, task="label rendering")
    labels = json.loads(SceneDir(job.scene).labels_report.read_text())
    accuracy = None
    if job.report:
        from .accuracy import label_accuracy

        accuracy = label_accuracy(job.scene)
        accuracy["method"] = method
        atomic_write_json(SceneDir(job.scene).labels_accuracy, accuracy)
    return {"labels": labels, "reconstruction": reconstruction, "accuracy": accuracy}


def child_job(data: dict, context: Any) -> dict:
    """The ``"labels"`` job of the child-process runtime (the bench's labels for a scene):
    ``data`` is a :class:`LabelJob` dict. Returns the number of views labelled and the
    accuracy report (None without ``report``)."""
    from ..config import config_from_dict

    job = config_from_dict(LabelJob, data, source=context.config_path)
    result = run_label_job(job, context.progress)
    return {"views": len(result["labels"]["views"]), "accuracy": result["accuracy"]}
