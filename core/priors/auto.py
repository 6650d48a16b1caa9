"""The ``auto`` prior source: the best depth and normals the images allow, per pixel, with a confidence.

``SCENE/priors/auto/`` is fused from the sources a user can compute (never ``gt`` depth):

1. **labels** (``esgs labels --reconstruct``: a mesh rebuilt by multi-view stereo, rendered):
   metric and sharp where stereo held, absent where the rebuilt mesh has holes;
2. **ndn** (the learned prior: the diffusion NDN's depth, the completion network's normals;
   :func:`..ndn.infer.write_ndn_priors`): dense but only relative; pinned to metric per view
   with a robust scale and shift fitted to the view's own SfM points;
3. **sfm** (the triangulated points): sparse, metric, verified by triangulation: the floor
   where neither dense source has a value.

Every dense source is checked per view against the SfM points the view observes (median
relative depth error, ``e``). The per-pixel confidence that scales the prior losses is the
rule documented in docs/priors.md ("The auto source"):

- labels: ``1 - e / max_error`` (0 when above ``max_error``: the view's labels are not used);
- ndn where labels are missing: ``ndn_trust * (1 - e / max_error)``; its depth there is the
  gradient fill (:mod:`.hole_fill`): NDN's shape, level with the labels at each hole's border
  and drawn to the SfM points inside it, unless those points prefer pinned NDN in that view
  (``fill_check``; ``hole_fill="pinned"``: NDN pinned to the points as it is, everywhere);
  in a view that looks across the ground (the camera's height over the plane through the view's
  nearer labels under ``ground_guide_height`` of their median depth) and whose nearer labels
  lie on that plane (a share ``ground_guide_inliers`` of them), where the plane meets the
  hole's rays at more than ``ground_guide_angle`` degrees it is the fill's shape instead of
  NDN's (:mod:`.ground_plane`: the near ground of rover views, where the network is weakest);
  with ``blend_second_depth`` (off by default), in views with sky (a share ``blend_min_sky`` of
  the pixels), where ``ndn`` also holds a second depth (its normals network's own, written by
  ``esgs priors --method ndn``), the holes take the geometric mean of the two depths, each
  filled that way: under the horizon one errs near and the other far; where only the second is
  trusted in such a view, it fills them alone (``second_depth_fallback``). Off because, though
  the prior is better on rover views, ESGS trained on it put far outliers off the real mesh
  (docs/priors.md, "Two networks' fills in views with sky");
- where both exist and differ by more than ``disagreement`` (relative), labels' confidence is
  halved: one of two independent estimates is wrong there;
- sfm points where no dense source has a value: confidence 1, depth only;
- sky: from the best mask that knows where there is no surface (``gt`` on synthetic scenes,
  else ``ndn``), the same order as the trainer's ``--mask-source auto``; no depth there.

What each source contributed, its coverage and its error against the SfM points are written
to ``priors/auto/auto.json``, with a fingerprint (contents, not times: a scene copied to
another machine keeps it) of the images, the model and the sources used: :func:`ensure_auto_priors` reuses the folder while the fingerprint holds, re-fuses when a
source changed, and recomputes the sources when the images or the model changed (and the
``ndn`` source when the package's own networks made it and have changed since).
"""
from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..errors import ConfigError, ESGSError
from ..formats.scene_dir import PriorSource, SceneDir
from ..io_utils import atomic_directory
from ..progress import ProgressCallback, ProgressEvent, no_progress
from .ground_plane import fit_view_plane, plane_depth
from .hole_fill import BORDER_FITS, DEFAULT_BORDER_TOLERANCE, DEFAULT_REACH, gradient_fill
from .pinning import MIN_PIN_SAMPLES, pin_relative_depth

#: ``priors/auto/auto.json``: what the fused folder was made from, per view and in total.
REPORT_NAME = "auto.json"
#: Fewer SfM points on a view's valid dense pixels than this and its error is unknown.
MIN_CHECK_POINTS = MIN_PIN_SAMPLES
#: Confidence of a dense source on a view whose error could not be checked (too few points).
UNCHECKED_CONFIDENCE = 0.5
#: Bumped when the fusion rule changes, so cached folders are rebuilt.
RULE_VERSION = 4
#: How NDN fills the labels' holes (``AutoPriorSettings.hole_fill``).
HOLE_FILLS = ("gradient", "pinned")


@dataclass
class AutoPriorSettings:
    """How ``priors/auto`` is fused (module docstring: the rule)."""

    max_error: float = field(default=0.15, metadata={
        "help": "a dense source whose depth disagrees with a view's SfM points by more than this median relative "
                "error is not used in that view (confidence falls linearly to 0 there)"})
    ndn_trust: float = field(default=0.5, metadata={
        "help": "NDN's confidence relative to stereo labels at the same error (a learned guess, not a measurement)"})
    disagreement: float = field(default=0.25, metadata={
        "help": "labels and NDN differing by more than this relative depth halve the labels' confidence there"})
    labels: bool = field(default=True, metadata={"help": "compute and use stereo labels (needs bpy)"})
    ndn: bool = field(default=True, metadata={"help": "compute and use NDN priors"})
    hole_fill: str = field(default="gradient", metadata={
        "help": "how NDN fills the labels' holes: 'gradient' keeps NDN's shape and meets the labels at each "
                "hole's border (esgs.core.priors.hole_fill), 'pinned' takes NDN pinned to the view's SfM points"})
    fill_reach: float = field(default=DEFAULT_REACH, metadata={
        "help": "with hole_fill 'gradient': how far into a hole the border's level carries, as a share of the "
                "image's longer side (beyond it the fill falls back to pinned NDN)"})
    fill_anchor_weight: float = field(default=1.0, metadata={
        "help": "with hole_fill 'gradient': pull of the SfM points inside holes (0 = none; 1 = as strong as one "
                "neighbour)"})
    fill_check: bool = field(default=True, metadata={
        "help": "with hole_fill 'gradient': keep pinned NDN in a view whose SfM points inside the holes it "
                "matches better than the gradient fill made without them"})
    fill_border_fit: str = field(default="plane", metadata={
        "help": "with hole_fill 'gradient': what a hole's border labels are checked against: their 'median' level, "
                "or a robust 'plane' of level over the image"})
    ground_guide_angle: float = field(default=5.0, metadata={
        "help": "with hole_fill 'gradient': in a hole, where the plane through the view's nearer labels meets the "
                "ray at more than this angle (degrees), fill with the plane's shape instead of NDN's (0 = never)"})
    ground_guide_height: float = field(default=0.3, metadata={
        "help": "the plane shapes holes only in views that look across the ground: the camera's height over that "
                "plane below this share of the median labelled depth (rover views; aerial views keep NDN's shape)"})
    ground_guide_inliers: float = field(default=0.8, metadata={
        "help": "the plane shapes holes only where it fits: at least this share of the nearer labels within 2 % "
                "of their range from it (flat ground; a crater's floor and walls keep NDN's shape)"})
    blend_second_depth: bool = field(default=False, metadata={
        "help": "blend ndn's second depth (its normals network's own) into the labels' holes of views with sky "
                "(off: a better prior on rover views, but ESGS trained on it left far outliers off the real mesh)"})
    blend_min_sky: float = field(default=0.02, metadata={
        "help": "with blend_second_depth, in views with at least this share of sky, the labels' holes take the "
                "geometric mean of the two networks' fills (ndn's depth and its second depth, each filled as above): "
                "near the horizon one errs near, the other far"})
    second_depth_fallback: bool = field(default=True, metadata={
        "help": "in those views, where the first depth is not trusted (too far off the SfM points) and the second "
                "is, the second alone fills the holes"})
    fill_border_tolerance: float = field(default=DEFAULT_BORDER_TOLERANCE, metadata={
        "help": "with hole_fill 'gradient': a label at a hole's border whose level (log of labels over NDN) is "
                "farther than this from what the rest of that border predicts there is not used (0 = use every border label)"})

    def validate(self) -> None:
        for name in ("max_error", "disagreement"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.ndn_trust <= 1:
            raise ConfigError(f"ndn_trust must be in [0, 1], got {self.ndn_trust}")
        if self.hole_fill not in HOLE_FILLS:
            raise ConfigError(f"hole_fill must be one of {', '.join(HOLE_FILLS)}, got {self.hole_fill!r}")
        if self.fill_reach <= 0:
            raise ConfigError(f"fill_reach must be > 0, got {self.fill_reach}")
        if self.fill_border_fit not in BORDER_FITS:
            raise ConfigError(f"fill_border_fit must be one of {', '.join(BORDER_FITS)}, got {self.fill_border_fit!r}")
        if not 0 <= self.ground_guide_angle < 90:
            raise ConfigError(f"ground_guide_angle must be in [0, 90) degrees, got {self.ground_guide_angle}")
        if self.ground_guide_height <= 0:
            raise ConfigError(f"ground_guide_height must be > 0, got {self.ground_guide_height}")
        if not 0 <= self.ground_guide_inliers <= 1:
            raise ConfigError(f"ground_guide_inliers must be in [0, 1], got {self.ground_guide_inliers}")
        if self.fill_border_tolerance < 0:
            raise ConfigError(f"fill_border_tolerance must be >= 0, got {self.fill_border_tolerance}")
        if self.fill_anchor_weight < 0:
            raise ConfigError(f"fill_anchor_weight must be >= 0, got {self.fill_anchor_weight}")
        if not 0 <= self.blend_min_sky <= 1:
            raise ConfigError(f"blend_min_sky must be in [0, 1], got {self.blend_min_sky}")


@dataclass
class FusedView:
    """One view's fused maps: depth [H,W] (0 = none), normal [H,W,3] (0 = none), mask [H,W]
    (a depth value exists), confidence [H,W] in [0,1], sky [H,W] or None, and per-source
    pixel shares and errors for the report."""

    depth: np.ndarray
    normal: np.ndarray
    mask: np.ndarray
    confidence: np.ndarray
    sky: Optional[np.ndarray]
    report: dict[str, Any]


def sfm_fit_error(depth: np.ndarray, valid: np.ndarray, sfm_depth: np.ndarray) -> tuple[float, int]:
    """Median |depth - sfm| / sfm over pixels with an SfM sample and a valid ``depth``, and
    how many there were (error NaN with fewer than :data:`MIN_CHECK_POINTS`)."""
    check = valid & (sfm_depth > 0) & (depth > 0)
    count = int(check.sum())
    if count < MIN_CHECK_POINTS:
        return float("nan"), count
    return float(np.median(np.abs(depth[check] - sfm_depth[check]) / sfm_depth[check])), count


def _view_trust(error: float, settings: AutoPriorSettings) -> float:
    """1 - error / max_error clipped to [0, 1]; :data:`UNCHECKED_CONFIDENCE` for an unknown error."""
    if not np.isfinite(error):
        return UNCHECKED_CONFIDENCE
    return float(np.clip(1.0 - error / settings.max_error, 0.0, 1.0))


def _gradient_filled(pinned: np.ndarray, known: np.ndarray, fill: np.ndarray, sfm_depth: np.ndarray,
                     settings: AutoPriorSettings) -> tuple[np.ndarray, dict[str, Any]]:
    """NDN's depth with the holes ``fill`` filled level with the labels ``known`` (module
    :mod:`.hole_fill`), and what was done. With ``fill_check`` and enough SfM points inside the
    holes, the fill made without them is first compared there with ``pinned``: where pinned NDN
    is the closer of the two (large holes on aerial views, where one scale and shift fits the
    whole view and a long walk along NDN's gradients drifts) it is kept as it is."""
    def filled(anchor_weight: float) -> np.ndarray:
        return gradient_fill(pinned, known, fill, anchors=sfm_depth, anchor_weight=anchor_weight,
                             reach=settings.fill_reach, border_tolerance=settings.fill_border_tolerance or None,
                             border_fit=settings.fill_border_fit)

    inside = fill & (sfm_depth > 0)
    note: dict[str, Any] = {"points_in_holes": int(inside.sum())}
    free = None
    if settings.fill_check and note["points_in_holes"] >= MIN_CHECK_POINTS:
        free = filled(0.0)  # the SfM points judge it: they must not have shaped it
        truth = sfm_depth[inside]
        note["gradient_error"] = float(np.median(np.abs(free[inside] - truth) / truth))
        note["pinned_error"] = float(np.median(np.abs(pinned[inside] - truth) / truth))
        if note["pinned_error"] <= note["gradient_error"]:
            note["used"] = "pinned"
            return pinned, note
    note["used"] = "gradient"
    anchored = free if free is not None and settings.fill_anchor_weight == 0 else filled(settings.fill_anchor_weight)
    return np.where(fill, anchored, pinned), note


def _ground_guided(guide: np.ndarray, labels_depth: np.ndarray, labels_valid: np.ndarray, fill: np.ndarray,
                   intrinsics: np.ndarray, settings: AutoPriorSettings) -> tuple[np.ndarray, dict[str, Any]]:
    """``guide`` with the plane of the view's nearer labels in the ``fill`` pixels whose rays
    meet it at more than ``settings.ground_guide_angle`` degrees, and what was done."""
    plane = fit_view_plane(labels_depth, labels_valid, intrinsics)
    if plane is None:
        return guide, {"share": 0.0, "reason": "too few labels for a plane"}
    height_share = plane.offset / float(np.median(labels_depth[labels_valid]))
    if height_share >= settings.ground_guide_height:
        # seen from above (an orbit or nadir view): the holes are patches amid the labels, where
        # a plane flattens relief the network does see (measured: worse than NDN's shape there)
        return guide, {"share": 0.0, "height_share": height_share, "reason": "not a view across the ground"}
    if plane.inlier_share < settings.ground_guide_inliers:
        # the near ground is not a plane (inside a crater): extending one would cut through it
        return guide, {"share": 0.0, "height_share": height_share, "inlier_share": plane.inlier_share,
                       "reason": "the nearer labels do not lie on a plane"}
    height, width = guide.shape
    depth, angle = plane_depth(plane, intrinsics, height, width)
    use = fill & (depth > 0) & (angle > settings.ground_guide_angle)
    note = {"share": float(use.sum() / max(int(fill.sum()), 1)), "inlier_share": plane.inlier_share,
            "height_share": height_share}
    return np.where(use, depth, guide).astype(np.float32), note


def _checked_learned_depth(learned: np.ndarray, relative: bool, mask: np.ndarray, sfm_depth: np.ndarray,
                           settings: AutoPriorSettings) -> tuple[Optional[np.ndarray], np.ndarray, dict[str, Any]]:
    """A network's depth made metric (a relative one pinned to the SfM points) and checked
    against them: (depth or None when it could not be pinned or is not trusted, its valid
    pixels, the report: error, points, trust)."""
    valid = mask & (learned > 0)
    pinned = pin_relative_depth(learned, valid, sfm_depth) if relative else np.where(valid, learned, 0.0).astype(np.float32)
    if pinned is None:
        return None, np.zeros_like(valid), {"error": float("nan"), "points": 0, "trust": 0.0,
                                            "reason": "could not be pinned"}
    error, points = sfm_fit_error(pinned, valid, sfm_depth)
    trust = settings.ndn_trust * _view_trust(error, settings)
    if trust <= 0:
        return None, np.zeros_like(valid), {"error": error, "points": points, "trust": trust}
    return pinned, valid & (pinned > 0), {"error": error, "points": points, "trust": trust}


def _holes_filled(learned: np.ndarray, fill: np.ndarray, labels_depth: Optional[np.ndarray], labels_valid: np.ndarray,
                  known: np.ndarray, sfm_depth: np.ndarray, intrinsics: Optional[np.ndarray],
                  settings: AutoPriorSettings, report: dict[str, Any]) -> np.ndarray:
    """``learned`` with the labels' holes ``fill`` shaped by the ground plane where it applies and
    levelled with the labels ``known`` by the gradient fill (``hole_fill`` "gradient" and some
    labels); what was done goes into ``report`` (``ground_guide``, ``fill``)."""
    if settings.hole_fill != "gradient" or not labels_valid.any():
        return learned
    if intrinsics is not None and settings.ground_guide_angle > 0 and fill.any():
        learned, report["ground_guide"] = _ground_guided(learned, labels_depth, labels_valid, fill, intrinsics, settings)
    learned, report["fill"] = _gradient_filled(learned, known, fill, sfm_depth, settings)
    return learned


def _blended(filled: np.ndarray, fill: np.ndarray, second: np.ndarray, second_valid: np.ndarray,
             labels_depth: Optional[np.ndarray], labels_valid: np.ndarray, known: np.ndarray, sfm_depth: np.ndarray,
             intrinsics: Optional[np.ndarray], settings: AutoPriorSettings) -> tuple[np.ndarray, dict[str, Any]]:
    """``filled`` (the first depth's fill of the holes ``fill``) replaced, where the checked
    ``second`` depth fills them too, by the geometric mean of both fills, each made the same way.

    Why: in views with sky the holes lie mostly on the far ground under the horizon, beyond the
    labels, where the diffusion NDN's fill (levelled with the labels' far edge) stays too near
    and the completion network, which reads the labels and SfM points, often lands too far
    (docs/priors.md, "Two networks' fills in views with sky")."""
    second = _holes_filled(second, second_valid & fill, labels_depth, labels_valid, known, sfm_depth, intrinsics,
                           settings, report={})  # how the second was filled is not reported apart
    both = fill & second_valid & (filled > 0) & (second > 0)
    mean = np.sqrt(np.maximum(filled, 1e-12) * np.maximum(second, 1e-12))
    return np.where(both, mean, filled).astype(np.float32), {"share": float(both.sum() / max(int(fill.sum()), 1))}


def fuse_view(sfm_depth: np.ndarray, labels: Any = None, ndn: Any = None, sky: Optional[np.ndarray] = None,
              settings: Optional[AutoPriorSettings] = None, intrinsics: Optional[np.ndarray] = None) -> FusedView:
    """Fuse one view (module docstring: the rule).

    ``sfm_depth`` [H,W] metric samples (0 = none); ``labels`` and ``ndn``:
    :class:`~.io.PriorMaps` at the same size, or None (ndn's depth may be relative: it is
    pinned here); ``sky`` [H,W] bool from the best surface mask, or None; ``intrinsics``
    [3,3] the camera matrix at the maps' size (None: no ground-plane guide).
    """
    settings = settings or AutoPriorSettings()
    height, width = sfm_depth.shape
    depth = np.zeros((height, width), np.float32)
    normal = np.zeros((height, width, 3), np.float32)
    confidence = np.zeros((height, width), np.float32)
    report: dict[str, Any] = {}
    free = np.ones((height, width), bool) if sky is None else ~sky

    labels_depth = ndn_depth = None
    labels_valid = ndn_valid = np.zeros((height, width), bool)
    if labels is not None and labels.depth is not None:
        labels_valid = labels.mask & (labels.depth > 0) & free
        labels_depth = labels.depth
        error, points = sfm_fit_error(labels_depth, labels_valid, sfm_depth)
        trust = _view_trust(error, settings)
        report["labels"] = {"error": error, "points": points, "trust": trust}
        if trust <= 0:
            labels_valid = np.zeros_like(labels_valid)
    second = None  # the ndn source's second depth, checked, in views with sky
    if ndn is not None and ndn.depth is not None:
        ndn_depth, ndn_valid, report["ndn"] = _checked_learned_depth(ndn.depth, ndn.relative_depth, ndn.mask & free,
                                                                     sfm_depth, settings)
        sky_share = float(sky.mean()) if sky is not None else 0.0
        if settings.blend_second_depth and ndn.second_depth is not None and sky_share >= settings.blend_min_sky:
            second = _checked_learned_depth(ndn.second_depth, ndn.second_relative_depth, ndn.mask & free, sfm_depth,
                                            settings)
            report["second"] = second[2]
            if second[0] is None:
                second = None
            elif ndn_depth is None and settings.second_depth_fallback:
                # the first depth is not trusted here: the second, which is, fills the holes alone
                ndn_depth, ndn_valid, report["ndn"] = second[0], second[1], {**second[2], "from": "second depth"}
                second = None

    if labels_depth is not None and labels_valid.any():
        trust = report["labels"]["trust"]
        conf = np.full((height, width), trust, np.float32)
        if ndn_depth is not None:
            both = labels_valid & ndn_valid
            differ = np.zeros_like(both)
            differ[both] = np.abs(labels_depth[both] - ndn_depth[both]) / labels_depth[both] > settings.disagreement
            conf[differ] *= 0.5
            report["labels"]["disagreeing_share"] = float(differ.sum() / max(int(both.sum()), 1))
        depth[labels_valid] = labels_depth[labels_valid]
        confidence[labels_valid] = conf[labels_valid]
        if labels.normal is not None:
            normal[labels_valid] = labels.normal[labels_valid]
    fill = np.zeros((height, width), bool)
    if ndn_depth is not None:
        fill = ndn_valid & (depth <= 0)
        known = np.where(labels_valid, depth, 0.0)
        ndn_depth = _holes_filled(ndn_depth, fill, labels_depth, labels_valid, known, sfm_depth, intrinsics, settings,
                                  report)
        if second is not None and fill.any():
            ndn_depth, report["blend"] = _blended(ndn_depth, fill, second[0], second[1], labels_depth, labels_valid,
                                                  known, sfm_depth, intrinsics, settings)
        depth[fill] = ndn_depth[fill]
        confidence[fill] = report["ndn"]["trust"]
        if ndn.normal is not None:
            normal[fill] = ndn.normal[fill]
    floor = (sfm_depth > 0) & (depth <= 0) & free
    depth[floor] = sfm_depth[floor]
    confidence[floor] = 1.0
    mask = depth > 0
    total = float(height * width)
    report["share"] = {
        "labels": float((labels_valid & mask).sum() / total) if labels_depth is not None else 0.0,
        "ndn": float(fill.sum() / total),
        "sfm": float(floor.sum() / total),
        "sky": float(sky.sum() / total) if sky is not None else 0.0,
    }
    report["coverage"] = float(mask.sum() / total)
    report["mean_confidence"] = float(confidence[mask].mean()) if mask.any() else 0.0
    return FusedView(depth=depth, normal=normal, mask=mask, confidence=confidence, sky=sky, report=report)


# --- the folder ---------------------------------------------------------------------------
def _fingerprint_files(root: Path, paths: list[Path]) -> str:
    """Of the files' names (relative to ``root``) and contents: copying a scene to another
    machine keeps it, touching a file without changing it keeps it, new pixels change it."""
    digest = hashlib.sha256()
    for path in paths:
        digest.update(f"{path.relative_to(root).as_posix()}\n".encode())
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()[:16]


def inputs_fingerprint(scene: Path) -> str:
    """Of the images and the COLMAP model: what the computed sources were made from."""
    folder = SceneDir(scene)
    images = sorted(p for p in folder.images.rglob("*") if p.is_file()) if folder.images.is_dir() else []
    model = sorted(p for p in folder.model.iterdir() if p.is_file()) if folder.model.is_dir() else []
    return _fingerprint_files(folder.root, images + model)


def source_fingerprint(scene: Path, source: str) -> str:
    """Of one source's folder (every map): changes when it is recomputed with other results."""
    root = SceneDir(scene).prior(source)
    return _fingerprint_files(root, sorted(p for p in root.rglob("*") if p.is_file())) if root.is_dir() else "missing"


def read_report(scene: Path) -> Optional[dict]:
    """``priors/auto/auto.json`` or None."""
    path = SceneDir(scene).prior(PriorSource.AUTO) / REPORT_NAME
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _labels_available() -> bool:
    return importlib.util.find_spec("bpy") is not None


def _compute_source(scene: Path, source: str, progress: ProgressCallback) -> Optional[str]:
    """Compute ``priors/<source>`` in this process; None when done, else why it was skipped."""
    try:
        if source == PriorSource.LABELS:
            if not _labels_available():
                return "Blender's bpy module is not importable here (pip install bpy==5.0.1)"
            from ..labels.pipeline import LabelJob, run_label_job

            run_label_job(LabelJob(scene=scene, reconstruct=True), progress)
        elif source == PriorSource.NDN:
            from ..ndn.infer import write_ndn_priors

            write_ndn_priors(scene, progress=progress)  # the shipped networks, unless the environment names others
        else:
            from ..colmap import read_model
            from .sfm import write_sfm_priors

            write_sfm_priors(scene, read_model(scene), progress=progress)
    except ESGSError as error:
        return f"{source} priors failed: {error.message}"
    return None


def _outdated(scene: Path, source: str) -> Optional[str]:
    """Why a source's existing folder must be computed again though the images did not change
    (the package's NDN networks changed since it was predicted), or None."""
    if source == PriorSource.NDN:
        from ..ndn.infer import outdated_ndn_priors

        return outdated_ndn_priors(scene)
    return None


def _say(progress: ProgressCallback, message: str) -> None:
    progress(ProgressEvent(0, 0, "auto priors", kind="message", message=message))


def ensure_auto_priors(scene: str | Path, progress: ProgressCallback = no_progress, *,
                       settings: Optional[AutoPriorSettings] = None, force: bool = False) -> dict:
    """``SCENE/priors/auto``, reused when its fingerprint holds, else made (module docstring).

    Missing sources are computed first (sfm always; labels when bpy is importable; ndn);
    when the images or the model changed since the folder was made, every computed source
    is recomputed. Returns the report (``auto.json``).
    """
    scene = Path(scene)
    settings = settings or AutoPriorSettings()
    settings.validate()
    folder = SceneDir(scene)
    if not folder.has_model():
        from ..errors import DatasetError

        raise DatasetError("not a scene folder (no sparse/0)", path=scene, hint="esgs priors SCENE --method auto")
    inputs = inputs_fingerprint(scene)
    previous = read_report(scene)
    # a report without the fingerprint (or none) says nothing about the sources' age
    stale_inputs = previous is not None and previous.get("inputs") not in (None, inputs)
    wanted = [PriorSource.SFM] + [s for s, on in ((PriorSource.LABELS, settings.labels),
                                                  (PriorSource.NDN, settings.ndn)) if on]
    skipped: dict[str, str] = {}
    for source in wanted:
        outdated = _outdated(scene, source) if folder.has_prior_maps(source, "depth") else None
        if force or stale_inputs or outdated or not folder.has_prior_maps(source, "depth"):
            why = "the images or the model changed" if stale_inputs else outdated or "missing"
            _say(progress, f"auto priors: computing {source} priors ({why})")
            reason = _compute_source(scene, source, progress)
            if reason:
                skipped[str(source)] = reason
                _say(progress, f"auto priors: {source} left out: {reason}")
    used = [str(s) for s in wanted if folder.has_prior_maps(s, "depth") and str(s) not in skipped]
    sources = {name: source_fingerprint(scene, name) for name in used}
    key = {"inputs": inputs, "sources": sources, "settings": asdict(settings), "rule": RULE_VERSION}
    if not force and previous is not None and all(previous.get(k) == v for k, v in key.items()) \
            and folder.has_prior_maps(PriorSource.AUTO, "depth"):
        _say(progress, f"auto priors: reusing {folder.prior(PriorSource.AUTO)}")
        return previous
    return build_auto_priors(scene, used, settings, progress, extra={**key, "skipped": skipped})


def view_sources(scene: Path, model: Any, image: Any, used: list[str]) -> tuple[np.ndarray, dict[str, Any]]:
    """One view's inputs to :func:`fuse_view`: its SfM depth samples [H, W] and the dense sources
    of ``used`` (labels, ndn) as :class:`~.io.PriorMaps` at the camera's size in the camera
    frame (None for a view the source did not cover)."""
    from .io import load_prior_maps
    from .sfm import sparse_depth_map

    camera = model.cameras[image.camera_id]
    maps: dict[str, Any] = {}
    for source in (PriorSource.LABELS, PriorSource.NDN):
        if str(source) in used:
            try:
                maps[source] = load_prior_maps(scene, source, image.name, size=(camera.width, camera.height),
                                               world_to_camera_rotation=image.rotation_matrix())
            except ESGSError:
                maps[source] = None  # a view the source did not cover
    return sparse_depth_map(model, image.image_id), maps


def build_auto_priors(scene: Path, used: list[str], settings: AutoPriorSettings,
                      progress: ProgressCallback = no_progress, extra: Optional[dict] = None) -> dict:
    """Fuse ``used`` sources into ``priors/auto`` (staged; replaces the folder when complete);
    ``extra`` goes into the report as it is (the cache key)."""
    from ..colmap import read_model
    from .io import load_prior_maps, write_prior_maps

    folder = SceneDir(scene)
    model = read_model(scene)
    images = model.sorted_images()
    sky_sources = [s for s in PriorSource.auto_mask_order() if s.masks_sky and folder.has_prior_maps(s, "mask")]
    folder.priors.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".auto.work.", dir=folder.priors))
    views: dict[str, Any] = {}
    try:
        for index, image in enumerate(images):
            camera = model.cameras[image.camera_id]
            size = (camera.width, camera.height)
            rotation = image.rotation_matrix()
            sfm, maps = view_sources(scene, model, image, used)
            sky, sky_from = None, None
            for source in sky_sources:
                try:
                    sky = load_prior_maps(scene, source, image.name, size=size, world_to_camera_rotation=rotation).sky
                except ESGSError:
                    continue
                if sky is not None:
                    sky_from = str(source)
                    break
            fused = fuse_view(sfm, maps.get(PriorSource.LABELS), maps.get(PriorSource.NDN), sky, settings,
                              intrinsics=camera.K())
            fused.report["sky_source"] = sky_from
            write_prior_maps(work, PriorSource.AUTO, image.name, depth=fused.depth, normal=fused.normal,
                             mask=fused.mask, confidence=fused.confidence, sky=fused.sky, units="sfm",
                             metadata={"note": f"fused from {', '.join(used)} (esgs.core.priors.auto)"})
            views[image.name] = fused.report
            progress(ProgressEvent(index + 1, len(images), "auto priors"))
        report = {"sources_used": used, "views": views, "summary": _summary(views), **(extra or {})}
        with atomic_directory(folder.prior(PriorSource.AUTO), overwrite=True) as staging:
            os.replace(SceneDir(work).prior(PriorSource.AUTO), staging)
            (staging / REPORT_NAME).write_text(json.dumps(report, indent=1, default=_json_default))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    _say(progress, summary_line(report))
    return report


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(type(value).__name__)


def _summary(views: dict[str, Any]) -> dict[str, Any]:
    """Means over views of each source's share and error, coverage and confidence."""
    def mean(values: list[float]) -> float:
        values = [v for v in values if v is not None and np.isfinite(v)]
        return float(np.mean(values)) if values else float("nan")

    summary: dict[str, Any] = {"views": len(views)}
    for source in ("labels", "ndn", "sfm", "sky"):
        summary[f"{source}_share"] = mean([v["share"][source] for v in views.values()])
    for source in ("labels", "ndn"):
        checked = [v[source] for v in views.values() if source in v]
        summary[f"{source}_error"] = mean([c["error"] for c in checked])
        summary[f"{source}_views_used"] = sum(1 for c in checked if c["trust"] > 0)
    fills = [v["fill"]["used"] for v in views.values() if "fill" in v]
    summary["fill_views_gradient"] = fills.count("gradient")  # the rest kept pinned NDN (fill_check)
    summary["fill_views_pinned"] = fills.count("pinned")
    summary["coverage"] = mean([v["coverage"] for v in views.values()])
    summary["mean_confidence"] = mean([v["mean_confidence"] for v in views.values()])
    return summary


def summary_line(report: dict) -> str:
    """One line: what the auto prior is made of."""
    s = report["summary"]
    parts = [f"{source} {100 * s[f'{source}_share']:.0f}%" for source in ("labels", "ndn", "sfm")
             if s.get(f"{source}_share", 0) > 0]
    errors = [f"{source} {100 * s[f'{source}_error']:.1f}% off the SfM points in {s[f'{source}_views_used']}/"
              f"{s['views']} views" for source in ("labels", "ndn") if np.isfinite(s.get(f"{source}_error", np.nan))]
    return (f"auto priors: {100 * s['coverage']:.0f}% of pixels ({', '.join(parts) or 'nothing'}), "
            f"mean confidence {s['mean_confidence']:.2f}, sky {100 * s['sky_share']:.0f}%"
            + (f"; {'; '.join(errors)}" if errors else ""))
