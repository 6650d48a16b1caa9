"""The sky: a learned environment map rendered behind every Gaussian.

Outdoor views see sky, which no surface explains. Without a model of it, either the sky is
dropped from the photometric loss (it then renders black) or Gaussians paint it, floating
anywhere between the camera and infinity and wrecking the geometry. :class:`SkyModel` is a
colour for every viewing direction, ``sigmoid(b + sum_{k>0} c_k Y_k(d))`` per channel with
real spherical harmonics ``Y_k`` up to degree 3 (15 coefficients per channel besides the
constant ``b``, a logit) of the world-space ray direction ``d``: smooth, like a sky's
gradient, so it cannot mimic terrain detail. The constant is its own parameter in logit
units so Adam moves the overall colour at the learning rate's pace (a sky far from its start
colour is reached in tens of steps, not thousands). The
image of a view is ``rendered colour + (1 - alpha) * sky(d)``: it shows only where the
Gaussians leave the pixel transparent, and the photometric loss trains it on every pixel.
Directions no training view saw are constrained by nothing but the bands' shapes, and the
degree-3 bands extrapolate there; :meth:`SkyModel.dirichlet_energy` (the ``sky_smooth``
loss term, ``--sky-smooth-weight``) pulls them towards the mean colour unless the data
asks for a gradient.

A run saves it as ``RUN/sky.json`` (its own file: ``point_cloud.ply`` holds the terrain
only) and in its checkpoints; evaluation and ``esgs render`` composite it the same way.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Optional

import torch

from ..errors import CheckpointError
from ..render.sh import num_sh_bases, sh_basis

SKY_FORMAT = "esgs-sky-1"


def ray_directions(viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[H, W, 3] world-space unit directions of the rays through the pixel centres.

    viewmat: [4, 4] world-to-camera (OpenCV axes); K: [3, 3] pinhole intrinsics.
    """
    return _directions_at(viewmat, K, torch.arange(width, dtype=torch.float32) + 0.5,
                          torch.arange(height, dtype=torch.float32) + 0.5)


#: :meth:`SkyModel.image` evaluates the sky on a grid whose samples are at most this far apart
#: (radians at the image centre, ~0.6 degrees) and at most :data:`IMAGE_MAX_STRIDE` pixels.
IMAGE_SPACING_RAD = 0.01
IMAGE_MAX_STRIDE = 8


def image_stride(K: torch.Tensor) -> int:
    """Pixel spacing of the sky's evaluation grid for intrinsics ``K``: 1 (every pixel) for wide
    pixels, up to :data:`IMAGE_MAX_STRIDE` for narrow ones (a 1920-pixel-wide view)."""
    focal = float(min(K[0, 0], K[1, 1]))
    return int(max(1, min(IMAGE_MAX_STRIDE, math.floor(IMAGE_SPACING_RAD * focal))))


def _coarse_positions(size: int, stride: int) -> torch.Tensor:
    """Pixel-centre coordinates (j + 0.5) of ``ceil((size - 1) / stride) + 1`` samples evenly spaced
    from the first to the last pixel, as ``interpolate(align_corners=True)`` places them."""
    count = max(2, -(-(size - 1) // stride) + 1)
    return torch.linspace(0.5, size - 0.5, count, dtype=torch.float32)


def _directions_at(viewmat: torch.Tensor, K: torch.Tensor, columns: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """[len(rows), len(columns), 3] world-space unit directions through the pixel positions given."""
    viewmat, K = viewmat.to(torch.float32), K.to(torch.float32)
    v, u = torch.meshgrid(rows.to(K.device), columns.to(K.device), indexing="ij")
    camera = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], dim=-1)
    # R^T applied to row vectors: camera -> world
    return torch.nn.functional.normalize(camera @ viewmat[:3, :3], dim=-1)


class SkyModel(torch.nn.Module):
    """Colour of the sky in every direction: spherical harmonics of ``degree`` (0..3) through a sigmoid,
    optionally plus a coarse direction grid.

    ``base`` [3]: the constant part, a logit; ``coefficients`` [K - 1, 3] (K = (degree + 1)^2):
    the directional bands, starting at 0 (a uniform sky of ``initial_color``). ``grid_rows`` > 0
    adds ``grid`` [grid_rows, 2 grid_rows, 3], logits on an equirectangular map of the world
    directions (elevation from the -z to the +z pole over the rows, azimuth over the columns,
    wrapping), read bilinearly and added to the harmonics: a term with local support, so a
    change in one part of the sky (a prior on directions no view saw, say) leaves the rest as
    it is, where every harmonic band spans the whole sphere. It starts at 0.
    """

    def __init__(self, degree: int = 3, initial_color: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 grid_rows: int = 0):
        super().__init__()
        if not 0 <= degree <= 3:
            raise ValueError(f"sky degree must be in 0..3, got {degree}")
        if grid_rows < 0 or grid_rows == 1:
            raise ValueError(f"sky grid rows must be 0 (no grid) or at least 2, got {grid_rows}")
        self.degree = int(degree)
        self.grid_rows = int(grid_rows)
        self.base = torch.nn.Parameter(torch.zeros(3))
        self.coefficients = torch.nn.Parameter(torch.zeros(num_sh_bases(degree) - 1, 3))
        self.grid = torch.nn.Parameter(torch.zeros(self.grid_rows, 2 * self.grid_rows, 3)) if self.grid_rows else None
        # l (l + 1) of each directional coefficient's band (the Laplace-Beltrami eigenvalue);
        # not persistent: derived from the degree, so saved files and checkpoints do not change
        bands = [band * (band + 1) for band in range(1, self.degree + 1) for _ in range(2 * band + 1)]
        self.register_buffer("band_eigenvalues", torch.tensor(bands, dtype=torch.float32), persistent=False)
        self.set_color(initial_color)

    def set_color(self, color: tuple[float, float, float] | torch.Tensor) -> None:
        """Make the sky uniformly ``color`` (RGB in [0, 1]; clamped away from 0 and 1 for the logit)."""
        color = torch.as_tensor(color, dtype=torch.float32).clamp(0.01, 0.99)
        with torch.no_grad():
            self.base.copy_(torch.log(color / (1 - color)).to(self.base))
            self.coefficients.zero_()
            if self.grid is not None:
                self.grid.zero_()

    def logits(self, directions: torch.Tensor, *, harmonics_grad: bool = True) -> torch.Tensor:
        """[..., 3] unit directions -> [..., 3] the colours' logits ``b + sum_k c_k Y_k(d)`` (+ the grid's).

        ``harmonics_grad=False``: the harmonic part is detached, so a loss on these logits moves the
        grid alone (how :class:`UnseenSkyPrior` keeps its pull local when there is a grid).
        """
        flat = directions.reshape(-1, 3).to(self.base)
        logits = self.base.expand(flat.shape[0], 3)
        if self.degree > 0:
            basis = sh_basis(self.degree, flat)[:, 1:]  # [P, K - 1]
            logits = logits + basis @ self.coefficients
        if not harmonics_grad:
            logits = logits.detach()
        if self.grid is not None:
            logits = logits + self.grid_logits(flat)
        return logits.reshape(*directions.shape[:-1], 3)

    def grid_logits(self, directions: torch.Tensor) -> torch.Tensor:
        """[P, 3] unit directions -> [P, 3] the grid's bilinear reading (0 without a grid)."""
        if self.grid is None:
            return directions.new_zeros(directions.shape[0], 3)
        azimuth = torch.atan2(directions[:, 1], directions[:, 0])  # (-pi, pi]
        elevation = torch.asin(directions[:, 2].clamp(-1.0, 1.0))  # [-pi/2, pi/2]
        # the first column again after the last, so azimuth -pi and pi read the same cells
        wrapped = torch.cat([self.grid, self.grid[:, :1]], dim=1).permute(2, 0, 1)[None]  # [1, 3, R, C + 1]
        x = azimuth / math.pi  # -1 .. 1 over the C + 1 columns (align_corners: the ends are cell centres)
        y = elevation / (0.5 * math.pi)
        sample = torch.stack([x, y], dim=-1).view(1, -1, 1, 2).to(self.grid)
        read = torch.nn.functional.grid_sample(wrapped, sample, mode="bilinear", padding_mode="border",
                                               align_corners=True)  # [1, 3, P, 1]
        return read[0, :, :, 0].T

    def forward(self, directions: torch.Tensor) -> torch.Tensor:
        """[..., 3] unit directions -> [..., 3] colours in (0, 1)."""
        return torch.sigmoid(self.logits(directions))

    def dirichlet_energy(self) -> torch.Tensor:
        """Scalar: the Dirichlet energy of the logit field on the unit sphere, summed over R, G, B,
        ``sum_{l>=1} l (l + 1) ||c_l||^2`` (``c_l``: the band's 2l + 1 coefficients of each channel).

        It is ``integral over the sphere of |grad_S f|^2 dOmega`` for the logit field ``f`` (its
        mean squared surface gradient is this over 4 pi): by Green's identity the integral is
        ``-integral f Laplacian_S f``, each degree-l harmonic is an eigenfunction of the
        Laplace-Beltrami operator with eigenvalue ``-l (l + 1)``, and the basis of
        :func:`~esgs.core.render.sh.sh_basis` is orthonormal over the sphere (its constants are the
        closed forms ``sqrt((2l + 1) / (4 pi) (l - |m|)! / (l + |m|)!)``, times sqrt 2 for m != 0;
        3DGS's sign flips of some functions change no norm), so the cross terms vanish and no
        per-band factor besides ``l (l + 1)`` appears. The closed form is exact and cheap (15
        coefficients a channel); tests check it against a quadrature of finite-difference surface
        gradients over a Fibonacci sphere. The constant ``base`` (the mean colour) costs nothing,
        and degree 3 costs 6 times what degree 1 does, so a weight on it keeps the directions no
        view saw near the mean colour and lets the data buy the low bands first. 0 at degree 0.
        """
        return (self.band_eigenvalues.to(self.coefficients)[:, None] * self.coefficients.square()).sum()

    def image(self, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, *,
              stride: Optional[int] = None) -> torch.Tensor:
        """[H, W, 3] the sky as one camera sees it.

        The logits are evaluated on a grid of every ``stride``-th pixel (the first and the last
        pixel of each row and column included; default :func:`image_stride`: samples ~0.6
        degrees apart, at most 8 pixels) and interpolated bilinearly in between; then the
        sigmoid. The field is a degree-3 harmonic of the direction, nearly linear over that
        spacing, so this differs from evaluating every pixel by less than 1e-4 in colour for skies
        as varied as runs learn (tests), at a small fraction of the cost at high resolution (a
        1920x1080 view has 2M rays). ``stride=1`` evaluates every pixel.
        """
        viewmat, K = viewmat.to(self.base.device), K.to(self.base.device)
        stride = image_stride(K) if stride is None else int(stride)
        if stride <= 1 or (width <= 2 * stride and height <= 2 * stride):
            return self(ray_directions(viewmat, K, width, height))
        columns = _coarse_positions(width, stride)
        rows = _coarse_positions(height, stride)
        logits = self.logits(_directions_at(viewmat, K, columns, rows))  # [h, w, 3]
        fine = torch.nn.functional.interpolate(logits.permute(2, 0, 1)[None], size=(height, width), mode="bilinear",
                                               align_corners=True)[0].permute(1, 2, 0)
        return torch.sigmoid(fine)

    def to_dict(self) -> dict[str, Any]:
        data = {"format": SKY_FORMAT, "kind": "envmap", "degree": self.degree,
                "base": self.base.detach().cpu().tolist(), "coefficients": self.coefficients.detach().cpu().tolist()}
        if self.grid is not None:
            data.update(grid_rows=self.grid_rows, grid=self.grid.detach().cpu().tolist())
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: Any = None) -> "SkyModel":
        if not isinstance(data, dict) or data.get("format") != SKY_FORMAT:
            raise CheckpointError("not a sky model (missing or unknown format tag)", path=source)
        model = cls(int(data["degree"]), grid_rows=int(data.get("grid_rows", 0)))  # files before the grid have none
        base = torch.tensor(data["base"], dtype=torch.float32)
        coefficients = torch.tensor(data["coefficients"], dtype=torch.float32).reshape(-1, 3)
        if base.shape != model.base.shape or coefficients.shape != model.coefficients.shape:
            raise CheckpointError(f"sky parameters have shapes {tuple(base.shape)} and {tuple(coefficients.shape)}, "
                                  f"expected {tuple(model.base.shape)} and {tuple(model.coefficients.shape)}",
                                  path=source)
        grid = torch.tensor(data["grid"], dtype=torch.float32) if model.grid is not None else None
        if grid is not None and grid.shape != model.grid.shape:
            raise CheckpointError(f"sky grid has shape {tuple(grid.shape)}, expected {tuple(model.grid.shape)}",
                                  path=source)
        with torch.no_grad():
            model.base.copy_(base)
            model.coefficients.copy_(coefficients)
            if grid is not None:
                model.grid.copy_(grid)
        return model


def fibonacci_sphere(count: int) -> torch.Tensor:
    """[count, 3] nearly uniform unit directions (the Fibonacci lattice on the sphere)."""
    index = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * index / count
    radius = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    angle = index * (math.pi * (3.0 - math.sqrt(5.0)))  # the golden angle
    return torch.stack([radius * torch.cos(angle), radius * torch.sin(angle), z], dim=-1).float()


class UnseenSkyPrior:
    """Directions no training ray looked along take the colour of the nearest directions that
    were seen as sky.

    The sky model's bands are fitted where the training views saw sky; elsewhere they
    extrapolate freely, and a held-out view turned towards such a direction (another azimuth
    of the horizon, say) sees whatever the degree-3 bands happen to do there. This prior
    samples the sphere (:func:`fibonacci_sphere`), finds the *unseen* directions (farther than
    ``radius`` from every training ray, sky or ground) and, for each, its ``neighbours``
    nearest *sky-seen* directions (within ``radius`` of a ray through a sky pixel; through
    any pixel when no mask marks sky), and penalises the mean squared difference of the
    logits, the targets detached: the unseen sky continues what the data shows nearby instead
    of being pulled to one mean colour (what :meth:`SkyModel.dirichlet_energy` does, which
    also flattens real gradients the views saw). Directions inside a view but behind opaque
    ground are neither: nothing is asked of them.
    """

    def __init__(self, unseen: torch.Tensor, seen: torch.Tensor, neighbours: torch.Tensor, samples: int):
        self.unseen = unseen          # [U, 3]
        self.seen = seen              # [S, 3]
        self.neighbours = neighbours  # [U, k] indices into seen
        self.samples = samples        # directions sampled on the sphere

    @classmethod
    def from_rays(cls, all_rays: torch.Tensor, sky_rays: torch.Tensor, *, samples: int = 2048,
                  radius_deg: float = 6.0, neighbours: int = 4) -> Optional["UnseenSkyPrior"]:
        """From [R, 3] unit directions of training rays (all pixels) and [Q, 3] of the sky pixels
        among them; None when no direction is unseen or none was seen as sky."""
        points = fibonacci_sphere(samples).to(all_rays)
        threshold = math.cos(math.radians(radius_deg))
        covered = max_cosine(points, all_rays) >= threshold
        sky_seen = max_cosine(points, sky_rays) >= threshold if len(sky_rays) else torch.zeros_like(covered)
        unseen, seen = points[~covered], points[sky_seen]
        if len(unseen) == 0 or len(seen) == 0:
            return None
        k = min(neighbours, len(seen))
        nearest = (unseen @ seen.T).topk(k, dim=1).indices
        return cls(unseen, seen, nearest, samples)

    @classmethod
    def from_views(cls, views: Any, marks_sky: bool, *, stride: int = 4) -> Optional["UnseenSkyPrior"]:
        """From training views (``viewmat``, ``K``, ``width``, ``height``, ``mask``): rays through
        every ``stride``-th pixel, the sky ones where the masks mark sky (every ray when they do not)."""
        all_rays, sky_rays = [], []
        for view in views:
            # only the pixels it keeps (a full-resolution ray grid is 25 MB a view at 1080p)
            rays = _directions_at(view.viewmat, view.K, torch.arange(0, view.width, stride, dtype=torch.float32) + 0.5,
                                  torch.arange(0, view.height, stride, dtype=torch.float32) + 0.5).reshape(-1, 3)
            all_rays.append(rays)
            if not marks_sky:
                sky_rays.append(rays)
            elif view.mask is not None:
                sky = ~view.mask[::stride, ::stride, 0].bool().reshape(-1)
                sky_rays.append(rays[sky.to(rays.device)])
        if not all_rays:
            return None
        return cls.from_rays(torch.cat(all_rays), torch.cat(sky_rays) if sky_rays else all_rays[0][:0])

    def to(self, device: torch.device | str) -> "UnseenSkyPrior":
        return UnseenSkyPrior(self.unseen.to(device), self.seen.to(device), self.neighbours.to(device), self.samples)

    def loss(self, sky: SkyModel) -> torch.Tensor:
        """Mean over unseen directions and channels of (logit - mean logit of its sky-seen neighbours)^2.

        With a grid in the sky model only the grid takes this gradient: the unseen directions are
        filled in locally and the harmonics, which every view's sky (and the sky behind a
        not-quite-opaque ground) reads, are left to the photometric loss.
        """
        unseen = sky.logits(self.unseen, harmonics_grad=sky.grid is None)
        with torch.no_grad():
            target = sky.logits(self.seen)[self.neighbours].mean(dim=1)
        return (unseen - target).square().mean()

    @property
    def unseen_fraction(self) -> float:
        """Share of the sphere no training ray looked along."""
        return len(self.unseen) / self.samples


def max_cosine(points: torch.Tensor, rays: torch.Tensor, chunk: int = 65_536) -> torch.Tensor:
    """[P] the largest cosine between each point and any ray (-1 when there are none)."""
    best = torch.full((len(points),), -1.0, dtype=points.dtype, device=points.device)
    for start in range(0, len(rays), chunk):
        best = torch.maximum(best, (points @ rays[start:start + chunk].T).max(dim=1).values)
    return best


def save_sky(path: str | Path, sky: SkyModel) -> Path:
    """Write ``sky`` as JSON, atomically."""
    from ..io_utils import atomic_write_json

    atomic_write_json(path, sky.to_dict())
    return Path(path)


def load_sky(path: str | Path) -> Optional[SkyModel]:
    """The sky model saved at ``path``, or None when the file does not exist (a run without one)."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise CheckpointError(f"cannot read the sky model: {err}", path=path) from err
    return SkyModel.from_dict(data, source=path)


def composite(image: torch.Tensor, alpha: torch.Tensor, sky_image: torch.Tensor) -> torch.Tensor:
    """[H, W, 3] ``image`` (rendered on a black background) over the sky: image + (1 - alpha) * sky."""
    return image + (1.0 - alpha) * sky_image
