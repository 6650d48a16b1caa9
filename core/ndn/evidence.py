"""Metric evidence for the completion network: SfM and stereo depth of the reference view.

A scene usually knows part of each view's depth already: triangulated SfM points (sparse,
metric, verified by several views) and, when ``esgs labels --reconstruct`` ran, stereo
labels (dense where multi-view stereo held, metric, with holes on textureless ground, far
range and sky). A network conditioned on that evidence (``NDNModelConfig.evidence``) only has
to complete it: fill the holes, give normals and mark the sky, in metres.

How evidence enters the network (4 channels at the working size, :func:`encode_evidence`):

- one *reference depth* per view, the median of its evidence depths (:func:`evidence_reference`);
- ``sfm_state``, ``sfm_valid``: ``clip(ln(d / reference) / c, -1, 1)`` at pixels holding an SfM
  point (the median of the points in the pixel), 0 elsewhere, and 1 / 0 for "has a point";
- ``stereo_state``, ``stereo_valid``: the same for the stereo labels.

The network's depth state is the log state relative to that same reference, so its output
is metric: ``depth = reference x exp(c x state)``. Without any evidence the reference is
unknown; the state is then relative (the log state's usual per-view reference), as for the
unconditioned weights.

Training draws, per triple, which evidence the network sees (:data:`EVIDENCE_MODES`, with
:data:`MODE_PROBABILITIES`): none, SfM only (thinned at random), SfM and stereo, or stereo
alone. Shards carry the SfM points triangulated from the rendered images at build time
(``sfm_depth``); stereo labels are *simulated* from the true depth (:func:`simulate_stereo`:
correlated relative noise of 0.2-2 %, holes in random blobs and beyond a random far range,
none on the sky), because running multi-view stereo on every training scene costs minutes
each. Evaluation uses real stereo labels.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch.nn import functional as F

#: Channels the evidence adds to the network's input.
EVIDENCE_CHANNELS = 4
#: What a training triple may see; evaluation names one of these too.
EVIDENCE_MODES = ("none", "sfm", "sfm_stereo", "stereo")
#: How often training draws each mode (same order). SfM is what every scene has; stereo alone
#: stands for scenes whose points are few or were not kept.
MODE_PROBABILITIES = (0.2, 0.35, 0.3, 0.15)


def bin_sparse_depth(uv: np.ndarray, depth: np.ndarray, image_size: tuple[int, int],
                     working_size: tuple[int, int]) -> np.ndarray:
    """Sparse depth at the working size: points at ``uv`` [K, 2] (pixel centres at +0.5 in an
    image of ``image_size`` (w, h)) with z depth ``depth`` [K] -> [h, w] float32, each cell the
    median depth of the points falling in it, 0 where none does."""
    width, height = working_size
    result = np.zeros((height, width), np.float32)
    uv, depth = np.asarray(uv, float).reshape(-1, 2), np.asarray(depth, float).reshape(-1)
    keep = np.isfinite(depth) & (depth > 0)
    if not keep.any():
        return result
    columns = np.floor(uv[keep, 0] * width / image_size[0]).astype(int)
    rows = np.floor(uv[keep, 1] * height / image_size[1]).astype(int)
    inside = (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
    cells = rows[inside] * width + columns[inside]
    values = depth[keep][inside]
    order = np.lexsort((values, cells))
    cells, values = cells[order], values[order]
    unique, start, counts = np.unique(cells, return_index=True, return_counts=True)
    lower = values[start + (counts - 1) // 2]
    upper = values[start + counts // 2]
    result.reshape(-1)[unique] = 0.5 * (lower + upper)
    return result


def evidence_reference(*maps: torch.Tensor) -> torch.Tensor:
    """Per view, the median of every positive value of the evidence ``maps`` (each [B, h, w],
    0 = none) -> [B]; 0 for a view without evidence."""
    batch = maps[0].shape[0]
    flat = torch.cat([m.reshape(batch, -1) for m in maps], dim=1)
    result = torch.zeros(batch, dtype=flat.dtype)
    for index in range(batch):
        values = flat[index][flat[index] > 0]
        if values.numel():
            result[index] = values.median()
    return result


def log_reference(depth: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The log state's own per-view reference (the geometric mean of the 2nd and 98th percentiles
    of the valid depths, as :func:`.data.depth_to_state`): depth, mask [B, h, w] -> [B]."""
    result = torch.ones(depth.shape[0], dtype=depth.dtype)
    for index in range(depth.shape[0]):
        values = depth[index][mask[index] & (depth[index] > 0)].double()
        if values.numel():
            low, high = torch.quantile(values, torch.tensor([0.02, 0.98], dtype=values.dtype))
            result[index] = float(math.sqrt(float(low) * float(high)))
    return result


def state_about(depth: torch.Tensor, reference: torch.Tensor, log_range: float) -> torch.Tensor:
    """``clip(ln(depth / reference) / c, -1, 1)`` where depth > 0, 0 elsewhere: [B, h, w], [B] -> [B, h, w]."""
    ratio = depth / reference.view(-1, 1, 1).clamp_min(1e-9)
    state = (torch.log(ratio.clamp_min(1e-9)) / log_range).clamp(-1.0, 1.0)
    return torch.where(depth > 0, state, torch.zeros_like(state))


def target_state(depth: torch.Tensor, mask: torch.Tensor, reference: torch.Tensor, log_range: float) -> torch.Tensor:
    """The depth branch's target: the log state about ``reference``, +1 (far) where there is no
    surface: depth, mask [B, h, w], reference [B] -> [B, 1, h, w]."""
    valid = mask & (depth > 0)
    state = state_about(torch.where(valid, depth, torch.zeros_like(depth)), reference, log_range)
    return torch.where(valid, state, torch.ones_like(state))[:, None]


def encode_evidence(sfm: torch.Tensor, stereo: torch.Tensor, reference: torch.Tensor,
                    log_range: float) -> torch.Tensor:
    """The network's evidence input: SfM and stereo depth [B, h, w] (0 = none), reference [B]
    -> [B, 4, h, w] (sfm state, sfm valid, stereo state, stereo valid; module docstring)."""
    return torch.stack([state_about(sfm, reference, log_range), (sfm > 0).to(sfm.dtype),
                        state_about(stereo, reference, log_range), (stereo > 0).to(stereo.dtype)], dim=1)


def depth_from_state(state: torch.Tensor, reference: torch.Tensor, log_range: float) -> torch.Tensor:
    """Metric depth from the log state about ``reference``: state [B, 1, h, w], reference [B]."""
    return reference.view(-1, 1, 1, 1) * torch.exp(log_range * state.clamp(-1.0, 1.0))


def _smooth_field(batch: int, height: int, width: int, cells: int, generator: torch.Generator) -> torch.Tensor:
    """Random low-frequency field [B, h, w] with unit-ish spread (bilinear up-sampling of a coarse grid)."""
    coarse = torch.randn((batch, 1, max(2, cells * height // max(width, 1)), cells), generator=generator)
    return F.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)[:, 0]


def simulate_stereo(depth: torch.Tensor, mask: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Stereo-like labels from the true depth: depth, mask [B, h, w] -> [B, h, w] (0 = hole).

    Per view: a spatially correlated relative error with a spread drawn in 0.2-2 % (stereo is
    wrong in patches, not per pixel); holes where a random smooth field is above a random
    level (10-50 % of the image: textureless ground, occlusions) and, for half the views,
    beyond a random far percentile (60-95 %: too far for the baseline); nothing on the sky.
    """
    batch, height, width = depth.shape
    uniform = torch.rand((batch, 4), generator=generator)
    sigma = (0.002 + 0.018 * uniform[:, 0]).view(-1, 1, 1)
    error = _smooth_field(batch, height, width, 8, generator) * sigma
    noisy = depth * (1.0 + error)
    blobs = _smooth_field(batch, height, width, 6, generator)
    hole_share = 0.1 + 0.4 * uniform[:, 1]
    surface = mask & (depth > 0)
    level = torch.stack([torch.quantile(b[m] if m.any() else b.reshape(-1), 1.0 - float(s))
                         for b, m, s in zip(blobs, surface, hole_share)])  # the share is of the surface
    keep = surface & (blobs < level.view(-1, 1, 1))
    for index in range(batch):
        if uniform[index, 2] < 0.5 and keep[index].any():
            far = torch.quantile(depth[index][keep[index]], float(0.6 + 0.35 * uniform[index, 3]))
            keep[index] &= depth[index] <= far
    return torch.where(keep, noisy, torch.zeros_like(noisy))


def thin_points(sfm: torch.Tensor, generator: torch.Generator, low: float = 0.3) -> torch.Tensor:
    """Keep a random share (``low``-1, drawn per view) of the SfM cells: [B, h, w] -> [B, h, w]."""
    keep_share = low + (1.0 - low) * torch.rand((sfm.shape[0], 1, 1), generator=generator)
    keep = torch.rand(sfm.shape, generator=generator) < keep_share
    return torch.where(keep, sfm, torch.zeros_like(sfm))


def draw_evidence(depth: torch.Tensor, mask: torch.Tensor, sfm: torch.Tensor, generator: torch.Generator,
                  log_range: float) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    """A training batch's evidence: true depth, mask and triangulated SfM depth [B, h, w] ->
    (evidence [B, 4, h, w], reference [B], the mode drawn for each triple).

    The reference is the evidence's median; a triple drawn without evidence (or whose drawn
    evidence came out empty) uses the log state's own reference (:func:`log_reference`).
    """
    batch = depth.shape[0]
    draws = torch.multinomial(torch.tensor(MODE_PROBABILITIES), batch, replacement=True, generator=generator)
    modes = [EVIDENCE_MODES[int(i)] for i in draws]
    use_sfm = torch.tensor([m in ("sfm", "sfm_stereo") for m in modes]).view(-1, 1, 1)
    use_stereo = torch.tensor([m in ("stereo", "sfm_stereo") for m in modes]).view(-1, 1, 1)
    points = torch.where(use_sfm, thin_points(sfm, generator), torch.zeros_like(sfm))
    stereo = torch.where(use_stereo, simulate_stereo(depth, mask, generator), torch.zeros_like(depth))
    reference = evidence_reference(points, stereo)
    missing = reference <= 0
    if missing.any():
        reference = torch.where(missing, log_reference(depth, mask), reference)
    return encode_evidence(points, stereo, reference, log_range), reference, modes
