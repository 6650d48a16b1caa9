"""Export a scene's depth priors in the layout of the 3DGS reference code's depth regularisation.

The reference code (graphdeco-inria ``gaussian-splatting``, trained with ``-d depths``) reads:

- ``SCENE/depths/<stem>.png``: one 16-bit grey PNG per image (``<stem>`` is the COLMAP image
  name without its extension, sub-folders kept); the value divided by 2^16 is a "mono" inverse
  depth, known up to a scale and an offset;
- ``SCENE/sparse/0/depth_params.json``: ``{stem: {"scale": s, "offset": o}}`` so that
  ``png / 2**16 * s + o`` is the inverse depth of the SfM model (1 / camera z). Its own
  ``utils/make_depth_scale.py`` fits them per image from the COLMAP points; views whose scale
  lies outside [0.2, 5] times the median scale are dropped from the depth loss.

Our priors are already depths in scene (SfM) units, so the map is exact rather than fitted:
every view is encoded with one common scale (the largest inverse depth of the export maps to
65535) and offset 0, so no view falls outside the median-scale window. A ``relative`` depth
source (known up to scale and shift) is first fitted per view to the scene's ``sfm`` priors'
inverse depths, with the median / mean absolute deviation fit ``make_depth_scale.py`` uses.

The reference code has no mask: a pixel without a prior is written as 0, which decodes to
inverse depth 0 (infinitely far). Export a dense source (``auto``, ``ndn``, ``labels``) for
training; a sparse ``sfm`` export leaves most pixels at 0.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..formats.scene_dir import SceneDir, image_stem

FORMATS = ("3dgs",)
#: the reference code's PNG divisor
PNG_DIVISOR = float(2 ** 16)
PNG_MAX = 2 ** 16 - 1


@dataclass(frozen=True)
class ExportResult:
    out: Path
    depths: Path
    depth_params: Path
    views: int
    scale: float
    coverage: float  # mean fraction of pixels with a value


def _inverse(depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    valid = mask & np.isfinite(depth) & (depth > 0)
    return np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)


def fit_scale_offset(source: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """``scale, offset`` with ``source * scale + offset ~ target``: medians matched, spreads (mean
    absolute deviation from the median) matched, as the reference ``make_depth_scale.py`` does."""
    t_source, t_target = float(np.median(source)), float(np.median(target))
    s_source = float(np.mean(np.abs(source - t_source)))
    s_target = float(np.mean(np.abs(target - t_target)))
    scale = s_target / s_source if s_source > 0 else 1.0
    return scale, t_target - t_source * scale


def export_3dgs_depths(scene_dir: str | Path, source: str, out: str | Path | None = None) -> ExportResult:
    """Write ``OUT/depths/<stem>.png`` and ``OUT/sparse/0/depth_params.json`` (``OUT`` defaults to the
    scene) from the ``source`` priors of every image of ``sparse/0``."""
    from ..colmap.io import read_model
    from ..formats.imageio import write_png
    from ..io_utils import atomic_write_json
    from .io import load_prior_maps

    scene = SceneDir(scene_dir)
    out = Path(out) if out is not None else scene.root
    model = read_model(scene.model, use_pycolmap=False)
    names = [image.name for image in model.sorted_images()]
    inverse: dict[str, np.ndarray] = {}
    for name in names:
        maps = load_prior_maps(scene.root, source, name)
        if maps.depth is None:
            raise DatasetError(f"the {source!r} priors hold no depth", path=scene.prior(source))
        values = _inverse(maps.depth, maps.mask)
        if maps.relative_depth:
            sfm = load_prior_maps(scene.root, "sfm", name, size=(values.shape[1], values.shape[0]))
            target = _inverse(sfm.depth, sfm.mask) if sfm.depth is not None else np.zeros_like(values)
            both = (values > 0) & (target > 0)
            if both.sum() < 3:
                raise DatasetError(f"view {name!r}: too few SfM depths to scale the relative {source!r} depth",
                                   path=scene.prior("sfm"), hint="run esgs priors SCENE --method sfm first")
            scale, offset = fit_scale_offset(values[both], target[both])
            values = np.where(values > 0, np.maximum(values * scale + offset, 0.0), 0.0)
        inverse[name] = values
    top = max((float(v.max()) for v in inverse.values()), default=0.0)
    if top <= 0:
        raise DatasetError(f"the {source!r} priors hold no valid depth", path=scene.prior(source))
    # png / 2^16 * scale = inverse depth, with the largest inverse depth at PNG_MAX
    scale = top * PNG_DIVISOR / PNG_MAX
    params = {}
    depths = out / "depths"
    coverage = []
    for name, values in inverse.items():
        stem = image_stem(name)
        code = np.clip(np.rint(values / top * PNG_MAX), 0, PNG_MAX).astype(np.uint16)
        path = depths / f"{stem}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_png(path, code)
        params[stem] = {"scale": scale, "offset": 0.0}
        coverage.append(float((values > 0).mean()))
    params_path = SceneDir(out).model / "depth_params.json"
    params_path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(params_path, params)
    return ExportResult(out=out, depths=depths, depth_params=params_path, views=len(params), scale=scale,
                        coverage=float(np.mean(coverage)) if coverage else 0.0)
