"""One priors job: compute a scene's prior maps with one method (sfm, ndn or auto), the same for
``esgs priors``, the Blender add-on and the bench (the ``"priors"`` job of the child-process
runtime, :func:`child_job`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from ..formats.scene_dir import PriorSource, SceneDir, names
from ..progress import ProgressCallback

#: The prior sources a priors job computes.
METHODS = names(PriorSource.computed())


@dataclass
class PriorsSettings:
    """One priors job (what the Blender add-on and the bench run in a child process)."""

    scene: Path = field(metadata={"help": "scene folder (images/ + sparse/0)"})
    method: str = field(default="sfm", metadata={"help": "prior source to compute", "choices": METHODS})
    max_error_px: float = field(default=2.0, metadata={"help": "sfm: drop points with a larger reprojection error"})
    min_track_length: int = field(default=2, metadata={"help": "sfm: drop points seen in fewer views"})
    weights: Optional[Path] = field(default=None, metadata={
        "help": "ndn: depth network, a weights file or model folder (default: shipped)"})
    normal_weights: Optional[str] = field(default=None, metadata={
        "help": "ndn: normals network, a weights file or model folder, or 'same' for the depth network's own "
                "(default: the shipped completion network when the depth network is the shipped one)"})
    steps: Optional[int] = field(default=None, metadata={"help": "ndn: DDIM steps (default: the model's)"})
    seed: int = field(default=0, metadata={"help": "ndn: seed of the starting noise"})
    force: bool = field(default=False, metadata={"help": "auto: recompute even when the cached priors/auto still holds"})

    def validate(self) -> None:
        from ..errors import ConfigError

        if self.method not in METHODS:
            raise ConfigError(f"unknown prior method {self.method!r}", hint=f"choose one of {', '.join(METHODS)}")


def compute_priors(settings: PriorsSettings, progress: ProgressCallback) -> tuple[int, Optional[str]]:
    """Write ``SCENE/priors/<method>/``; returns (views written, the NDN weights used, in words, or None)."""
    settings.validate()
    if settings.method == "auto":
        from .auto import ensure_auto_priors

        report = ensure_auto_priors(settings.scene, progress, force=settings.force)
        return int(report["summary"]["views"]), None
    if settings.method == "ndn":
        from ..ndn.infer import write_ndn_priors
        from ..ndn.shipped import resolve_prior_networks

        networks = resolve_prior_networks(settings.weights, settings.normal_weights)
        count = write_ndn_priors(settings.scene, settings.weights, normal_weights=settings.normal_weights,
                                 steps=settings.steps, seed=settings.seed, progress=progress)
        used = str(networks.depth) + (f"; normals: {networks.normals}" if networks.normals else "")
        return count, used
    from ..colmap import read_model
    from .sfm import write_sfm_priors

    model = read_model(settings.scene)
    return write_sfm_priors(settings.scene, model, progress=progress, max_error_px=settings.max_error_px,
                            min_track_length=settings.min_track_length), None


def child_job(data: dict, context: Any) -> dict:
    """The ``"priors"`` job of the child-process runtime: ``data`` is a :class:`PriorsSettings`
    dict. The runtime turns a stop request into KeyboardInterrupt, on which the writers remove
    their staging folders (the previous priors are kept). Returns ``{"views", "weights", "folder"}``."""
    from ..config import config_from_dict
    from ..progress import ProgressEvent

    settings = config_from_dict(PriorsSettings, data, source=context.config_path)
    count, weights = compute_priors(settings, context.progress)
    folder = SceneDir(settings.scene).prior(settings.method)
    line = f"wrote {settings.method} priors for {count} views to {folder}"
    context.progress(ProgressEvent(count, count, f"{settings.method} priors", kind="done", message=line))
    return {"views": count, "weights": weights, "folder": str(folder)}
