"""Filling the pixels a label render missed, with the filled pixels flagged.

A mesh rendered from a camera leaves pixels without a surface in two situations: real
"no surface" (sky, the view running off the reconstructed area at the image border) and
holes in the mesh (a gap of the reconstruction, a cut where triangles were too long). The
second kind is what the label pipeline fills; the first must stay empty, or the labels
would invent ground where there is none.

Which pixels are filled (:func:`fill_region`):

- every connected region of missing pixels (8-connected) that does NOT touch the image
  border and covers at most ``max_hole_fraction`` of the image: an enclosed hole, ground
  all around it;
- optionally (``edge_radius_px`` > 0; off by default) missing pixels within that many
  pixels of a rendered one, also at the border: ragged mesh edges. Off by default because
  next to a horizon it would grow the ground into the sky.

How (:func:`fill_missing`): membrane (Laplace) interpolation of inverse depth and of the
normal components from the rendered pixels around each hole (:func:`membrane_fill`, one
sparse linear solve), then the normals are renormalised. Inverse depth is linear in the
pixel coordinates on a plane, and linear functions solve Laplace's equation, so a hole in a
plane is filled with exactly that plane. (OpenCV's ``cv2.inpaint`` was tried first: on
float32 depth its Telea variant returned oscillating garbage in 4.11.)

The mask is honest: 255 = rendered from the mesh, :data:`FILLED` (128) = filled here,
0 = no label. Readers that only ask "valid or not" (``> 127``) get both rendered and
filled pixels, like the paper's dense labels; ``filled`` pixels can be told apart.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError

RENDERED = 255
FILLED = 128
EMPTY = 0


@dataclass
class FillOptions:
    """How missing label pixels are filled (see the module docstring)."""

    max_hole_fraction: float = field(default=0.05, metadata={
        "help": "fill enclosed holes up to this fraction of the image area (0 = no hole filling)"})
    edge_radius_px: int = field(default=0, metadata={
        "help": "also fill missing pixels within this many pixels of a rendered one (0 = off)"})

    def validate(self) -> None:
        if not 0.0 <= self.max_hole_fraction <= 1.0:
            raise ConfigError(f"max_hole_fraction must be in [0, 1], got {self.max_hole_fraction}")
        if self.edge_radius_px < 0:
            raise ConfigError(f"edge_radius_px must be >= 0, got {self.edge_radius_px}")


def fill_region(valid: np.ndarray, options: FillOptions | None = None) -> np.ndarray:
    """[H, W] bool: the missing pixels of ``valid`` [H, W] bool that are to be filled."""
    import cv2

    options = options or FillOptions()
    valid = np.asarray(valid, bool)
    missing = ~valid
    region = np.zeros_like(valid)
    if not valid.any() or not missing.any():
        return region
    height, width = valid.shape
    if options.max_hole_fraction > 0:
        count, labels, stats, _ = cv2.connectedComponentsWithStats(missing.astype(np.uint8), connectivity=8)
        left, top = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
        right, bottom = left + stats[:, cv2.CC_STAT_WIDTH], top + stats[:, cv2.CC_STAT_HEIGHT]
        enclosed = (left > 0) & (top > 0) & (right < width) & (bottom < height)
        small = stats[:, cv2.CC_STAT_AREA] <= options.max_hole_fraction * height * width
        chosen = enclosed & small
        chosen[0] = False  # label 0 is the valid pixels
        region |= chosen[labels] & missing
    if options.edge_radius_px > 0:
        distance = cv2.distanceTransform(missing.astype(np.uint8), cv2.DIST_L2, 5)
        region |= missing & (distance <= options.edge_radius_px)
    return region


def fill_missing(depth: np.ndarray, normal: np.ndarray, valid: np.ndarray,
                 options: FillOptions | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fill the holes of one rendered view.

    depth: [H, W] float32, 0 = no surface; normal: [H, W, 3] float32 unit vectors (0 where
    no surface); valid: [H, W] bool, the rendered surface pixels.
    Returns (depth [H, W] float32, normal [H, W, 3] float32, mask [H, W] uint8 with
    255 rendered / 128 filled / 0 empty). Rendered pixels are returned unchanged.
    """

    options = options or FillOptions()
    options.validate()
    valid = np.asarray(valid, bool)
    depth = np.asarray(depth, np.float32)
    normal = np.asarray(normal, np.float32)
    region = fill_region(valid, options)
    mask = np.where(valid, RENDERED, EMPTY).astype(np.uint8)
    out_depth = np.where(valid, depth, 0.0).astype(np.float32)
    out_normal = np.where(valid[..., None], normal, 0.0).astype(np.float32)
    if not region.any():
        return out_depth, out_normal, mask
    inverse = np.where(valid, 1.0 / np.maximum(out_depth, 1e-12), 0.0)
    known = np.concatenate([inverse[..., None], out_normal.astype(np.float64)], axis=-1)  # [H, W, 4]
    filled = membrane_fill(known, valid, region)
    filled_inverse, filled_normal = filled[..., 0], filled[..., 1:]
    length = np.linalg.norm(filled_normal, axis=-1, keepdims=True)
    filled_normal = filled_normal / np.maximum(length, 1e-12)
    good = region & (filled_inverse > 0) & (length[..., 0] > 1e-3)
    out_depth[good] = (1.0 / filled_inverse[good]).astype(np.float32)
    out_normal[good] = filled_normal[good].astype(np.float32)
    mask[good] = FILLED
    return out_depth, out_normal, mask


def membrane_fill(values: np.ndarray, known: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Harmonic (Laplace) interpolation of ``values`` [H, W, C] over ``region`` [H, W] bool.

    The filled values solve the discrete Laplace equation (each region pixel the mean of its
    4-neighbours) with the ``known`` [H, W] bool pixels as fixed boundary values; neighbours
    that are neither known nor in the region (sky, outside the image) are left out of the
    mean (a free boundary). Linear functions of the pixel coordinates are harmonic, so a hole
    in a plane's inverse depth is filled exactly. Returns a copy of ``values`` with the region
    filled. Every connected part of ``region`` must touch a known pixel (as
    :func:`fill_region` guarantees).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    values = np.array(values, dtype=np.float64)
    height, width = region.shape
    index = -np.ones((height, width), np.int64)
    rows, cols = np.nonzero(region)
    count = len(rows)
    if count == 0:
        return values
    index[rows, cols] = np.arange(count)
    entries_row, entries_col, entries_value = [], [], []
    degree = np.zeros(count)
    rhs = np.zeros((count, values.shape[-1]))
    for d_row, d_col in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        n_row, n_col = rows + d_row, cols + d_col
        inside = (n_row >= 0) & (n_row < height) & (n_col >= 0) & (n_col < width)
        n_row_c, n_col_c = np.clip(n_row, 0, height - 1), np.clip(n_col, 0, width - 1)
        neighbour_known = inside & known[n_row_c, n_col_c]
        neighbour_free = inside & region[n_row_c, n_col_c]
        degree += neighbour_known | neighbour_free
        rhs[neighbour_known] += values[n_row_c[neighbour_known], n_col_c[neighbour_known]]
        entries_row.append(np.nonzero(neighbour_free)[0])
        entries_col.append(index[n_row_c[neighbour_free], n_col_c[neighbour_free]])
        entries_value.append(-np.ones(int(neighbour_free.sum())))
    diagonal = np.arange(count)
    matrix = coo_matrix((np.concatenate([degree, *entries_value]),
                         (np.concatenate([diagonal, *entries_row]), np.concatenate([diagonal, *entries_col]))),
                        shape=(count, count)).tocsc()
    solution = spsolve(matrix, rhs)
    values[rows, cols] = solution.reshape(count, -1)
    return values
