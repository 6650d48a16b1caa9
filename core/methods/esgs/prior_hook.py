"""Trainer hook that adds the ESGS geometry losses (depth prior, normal prior, consistency)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
import torch

from ...errors import ConfigError
from ...priors import load_prior_maps
from ...priors.align import align_depth_to_points
from ...priors.losses import (depth_loss, depth_normal_consistency_loss, edge_aware_weights, incidence_weights,
                              normal_loss, sky_loss, thinness_loss)
from ...priors.seeding import lift_pixels, sample_prior_pixels
from ...render import MEDIAN_SURFACE_BACKENDS
from ...render.surface import median_surface_depth, median_surface_normals, median_surface_thinness
from ...train.hooks import RunView, SeedPoints, TrainHook
from ...train.losses import LossContext, LossTerm, flattening_loss
from .config import ESGSConfig


@dataclass
class ViewPriors:
    """The priors of one training view, on the run's device, at the view's resolution.

    depth: [H, W] scene units (``relative``: known up to scale and shift) or None; normal:
    [H, W, 3] unit normals, camera frame (OpenCV axes) or None; mask: [H, W] bool, where the
    prior losses act; sky: [H, W] bool, pixels with no surface (the sky loss), or None;
    far: the view's far surface distance (scene units; a 0-dim tensor) or None; confidence:
    [H, W] trust in [0, 1] scaling both prior losses per pixel (the ``auto`` source), or None;
    depth_confidence: [H, W] the depth loss's own weights where they differ from ``confidence``
    (``depth_incidence``), or None; valid: [H, W] bool, the prior map's own mask and the view's
    (``mask`` before ``use_masks`` off widens it and ``max_prior_depth`` narrows it): where a
    seeded Gaussian may come from.
    """

    depth: Optional[torch.Tensor]
    normal: Optional[torch.Tensor]
    mask: torch.Tensor
    relative: bool = False
    sky: Optional[torch.Tensor] = None
    far: Optional[torch.Tensor] = None
    confidence: Optional[torch.Tensor] = None
    depth_confidence: Optional[torch.Tensor] = None
    valid: Optional[torch.Tensor] = None

    @property
    def depth_trust(self) -> Optional[torch.Tensor]:
        """The per-pixel weights of the depth loss: ``depth_confidence`` when set, else ``confidence``."""
        return self.depth_confidence if self.depth_confidence is not None else self.confidence


#: Mixed into the run's seed for the draw of the seeded pixels (its own stream: the run's
#: generator is not touched, so seeding changes nothing else of a run).
_SEED_SALT = 0x5EED


class PriorLossHook(TrainHook):
    """Loads ``priors/<source>/`` for every training view and adds the loss terms.

    Prior maps are loaded once at setup, brought to each view's training resolution, and
    kept as tensors. Pixels outside the prior's mask (and the view's own mask) never count.
    """

    name = "esgs_priors"

    def __init__(self, config: ESGSConfig):
        self.config = config
        self.priors: dict[str, ViewPriors] = {}
        self._weights: dict[str, torch.Tensor] = {}
        self.normal_render = config.normal_render  # what the run's backend can give (setup)
        self._depth_span = (0, 1)  # the steps over which the depth weight decays (setup)

    # ------------------------------------------------------------------------------
    def initial_points(self, run: RunView) -> Optional[SeedPoints]:
        """``prior_points`` pixels of each training view's metric depth prior, lifted into the
        scene: inside the prior's mask and the view's, never sky, drawn in proportion to the
        prior's confidence (uniformly without one); coloured by the view's image."""
        if self.config.prior_points <= 0 or not self.config.priors:
            return None
        self._load(run)
        rng = np.random.default_rng((int(run.seed) * 1_000_003 + _SEED_SALT) % (2 ** 63))
        xyz, rgb = [], []
        for view in run.train_views:
            prior = self.priors.get(view.name)
            if prior is None or prior.depth is None or prior.relative:
                continue
            depth = prior.depth.cpu().numpy()
            # the map's own mask even with use_masks off: no seed from sky or a missing value
            inside = prior.valid if prior.valid is not None else prior.mask
            valid = inside.cpu().numpy() & np.isfinite(depth) & (depth > 0)
            if prior.sky is not None:
                valid &= ~prior.sky.cpu().numpy()
            if self.config.max_prior_depth > 0:
                valid &= depth <= self.config.max_prior_depth
            weights = prior.confidence.cpu().numpy() if prior.confidence is not None else None
            rows, cols = sample_prior_pixels(valid, self.config.prior_points, rng, weights)
            if rows.size == 0:
                continue
            xyz.append(lift_pixels(depth, rows, cols, view.K.double().numpy(), view.viewmat.double().numpy()))
            rgb.append(view.image[rows, cols].numpy().astype(np.float64) / 255.0)
        if not xyz:
            run.message(f"note: prior source {self.config.priors!r} has no metric depth to seed Gaussians from")
            return None
        seeds = SeedPoints(xyz=np.concatenate(xyz), rgb=np.concatenate(rgb))
        run.message(f"seeded {len(seeds.xyz):,} Gaussians from the {self.config.priors} depth prior "
                    f"({len(xyz)} views)")
        return seeds

    def setup(self, run: RunView) -> None:
        config = self.config
        start = run.scaled_step(config.prior_start_step)
        wants_sky = config.sky_loss_on
        if config.depth and config.depth_render != "expected" and run.backend not in MEDIAN_SURFACE_BACKENDS:
            raise ConfigError(f"depth_render {config.depth_render!r} needs the median surface of each pixel, which "
                              "only the cpu and reference rasterizer backends return",
                              hint="train with --backend cpu, or set --depth-render expected")
        self.normal_render = config.normal_render
        if config.normal and self.normal_render != "composited" and run.backend not in MEDIAN_SURFACE_BACKENDS:
            # the default: a cuda run still gets a normal prior, the one its rasterizer can give
            run.message(f"note: normal_render {config.normal_render!r} needs the median surface of each pixel, "
                        f"which the {run.backend} backend does not return; the normal prior meets the composited "
                        "normal in this run (--backend cpu for the median surface)")
            self.normal_render = "composited"
        if (config.depth or config.normal or wants_sky) and not self.priors:  # initial_points may have loaded them
            self._load(run)
        if config.depth:
            self._depth_span = (start, max(run.scaled_step(30_000), start + 1))
            run.add_loss_term(LossTerm("depth_prior", config.depth_weight, self._depth_term, start_step=start,
                                       needs=frozenset({"depth"}), densifies=False))
        if config.normal:
            # the median surface's normals are read from the Gaussians, not rendered
            needs = frozenset({"normals"}) if self.normal_render == "composited" else frozenset()
            run.add_loss_term(LossTerm("normal_prior", config.normal_weight, self._normal_term, start_step=start,
                                       needs=needs, densifies=False))
        if config.flatten_weight > 0:
            extent = run.extent
            run.add_loss_term(LossTerm("flatten", config.flatten_weight,
                                       lambda context: flattening_loss(context.params.scales, extent),
                                       start_step=start, densifies=False))
        if wants_sky and any(p.sky is not None for p in self.priors.values()):
            run.add_loss_term(LossTerm("sky", config.sky_weight, self._sky_term, start_step=start,
                                       needs=frozenset({"depth"}), densifies=False))
        elif wants_sky:
            run.message(f"note: prior source {config.priors!r} marks no sky pixels (mask_kind coverage, or no "
                        "sky in view); the sky loss is off")
        if config.consistency:
            run.add_loss_term(LossTerm("depth_normal", config.consistency_weight, self._consistency_term,
                                       start_step=run.scaled_step(config.consistency_start_step),
                                       needs=frozenset({"depth", "normals"}), densifies=False))

    def _load(self, run: RunView) -> None:
        source = self.config.priors
        device = run.device
        alignments = []
        for view in run.train_views:
            rotation = view.viewmat[:3, :3].double().numpy()
            maps = load_prior_maps(run.scene, source, view.name,
                                   size=(view.width, view.height), world_to_camera_rotation=rotation)
            mask = torch.from_numpy(maps.mask.copy())
            valid = mask & view.mask[..., 0].bool() if view.mask is not None else mask
            if not self.config.use_masks:
                mask = torch.ones_like(mask)
            depth = torch.from_numpy(maps.depth.copy()) if maps.depth is not None else None
            if view.mask is not None and self.config.use_masks:
                mask = mask & view.mask[..., 0].bool()
            normal = torch.from_numpy(maps.normal.copy()) if maps.normal is not None else None
            relative = bool(maps.relative_depth)
            if depth is not None and relative and self.config.relative_alignment == "sfm":
                alignment = align_depth_to_points(depth, mask, view.K, view.viewmat, view.observed_xyz)
                alignments.append((view.name, alignment))
                if alignment.depth is not None:
                    depth, relative = alignment.depth, False
                if _failed_prediction(alignment, self.config.max_alignment_error):
                    # the prediction contradicts the image's own triangulated points: its
                    # normals come from the same failed prediction, so neither is used
                    depth = normal = None
            # a depth limit is in scene units: it cannot apply to a prior still relative
            if depth is not None and not relative and self.config.max_prior_depth > 0:
                mask = mask & (depth <= self.config.max_prior_depth)
            sky = self._sky_pixels(maps.sky, view, failed=depth is None and normal is None)
            confidence = torch.from_numpy(maps.confidence.copy()) if maps.confidence is not None else None
            depth_confidence = None
            if depth is not None and normal is not None and self.config.depth_incidence > 0:
                grazing = incidence_weights(normal, view.K, self.config.depth_incidence)
                depth_confidence = (grazing * confidence if confidence is not None else grazing).to(device)
            self.priors[view.name] = ViewPriors(
                depth=depth.to(device) if depth is not None else None,
                normal=normal.to(device) if normal is not None else None,
                mask=mask.to(device),
                relative=relative,
                sky=sky.to(device) if sky is not None else None,
                far=_far_depth(depth, mask) if depth is not None and not relative else None,
                confidence=confidence.to(device) if confidence is not None else None,
                depth_confidence=depth_confidence,
                valid=valid,
            )
        if alignments:
            run.message(_alignment_summary(alignments, self.config.max_alignment_error))
        if self.config.depth and all(p.depth is None for p in self.priors.values()):
            run.message(f"warning: prior source {source!r} has no depth maps; the depth loss stays at zero")
        if self.config.normal and all(p.normal is None for p in self.priors.values()):
            run.message(f"warning: prior source {source!r} has no normal maps; the normal loss stays at zero")

    def _sky_pixels(self, sky: Any, view: Any, *, failed: bool) -> Optional[torch.Tensor]:
        """[H,W] bool sky pixels of a view, or None: unknown, masks off, or the view's prediction
        was dropped by the confidence gate (its sky comes from the same failed prediction)."""
        if sky is None or failed or not self.config.use_masks or self.config.sky_weight <= 0:
            return None
        sky = torch.from_numpy(sky.copy())
        if view.mask is not None:
            sky = sky & view.mask[..., 0].bool()  # masked-out pixels (rover hardware) are no sky
        return sky if bool(sky.any()) else None

    def _edge_weights(self, context: LossContext) -> torch.Tensor:
        name = context.view.name
        if name not in self._weights:
            if self.config.edge_strength > 0:
                self._weights[name] = edge_aware_weights(context.target, self.config.edge_strength)
            else:
                self._weights[name] = torch.ones(context.target.shape[:2], device=context.target.device)
        return self._weights[name]

    # --- loss terms ------------------------------------------------------------------
    def _depth_term(self, context: LossContext) -> torch.Tensor:
        prior = self.priors.get(context.view.name)
        if prior is None or prior.depth is None or context.depth is None:
            return context.image.sum() * 0.0
        if self.config.depth_render == "expected":
            depth, mask, alpha = context.depth[..., 0], prior.mask, context.alpha[..., 0]
        else:
            depth, surface = self._median_depth(context)
            mask, alpha = prior.mask & surface, None  # a median surface exists only where alpha > 0.5
        loss = depth_loss(depth, prior.depth, mask, self._edge_weights(context), mode=self.config.depth_mode,
                          relative=prior.relative, alpha=alpha, confidence=prior.depth_trust,
                          robust=self.config.depth_robust)
        return loss * self._depth_decay_factor(context.step)

    def _depth_decay_factor(self, step: int) -> float:
        """``depth_decay`` ** (progress from the prior start step to the run's last step)."""
        if self.config.depth_decay == 1.0:
            return 1.0
        first, last = self._depth_span
        progress = min(max((step - first) / (last - first), 0.0), 1.0)
        return float(self.config.depth_decay) ** progress

    def _median_depth(self, context: LossContext) -> tuple[torch.Tensor, torch.Tensor]:
        """The depth of each pixel's median surface (``depth_render`` plane or centre) and where it exists."""
        ids = self._median_ids(context, f"depth_render {self.config.depth_render!r}", "--depth-render expected")
        params, view = context.params, context.view
        return median_surface_depth(ids[0], params.means, params.quats, params.scales, view.viewmat, view.K,
                                    kind=self.config.depth_render)

    @staticmethod
    def _median_ids(context: LossContext, setting: str, fix: str) -> torch.Tensor:
        ids = context.output.meta.get("median_ids") if context.output is not None else None
        if ids is None:
            raise ConfigError(f"{setting}: the rasterizer returned no median surface ids (only the cpu and "
                              "reference backends do)", hint=f"train with --backend cpu, or set {fix}")
        return ids

    def _normal_term(self, context: LossContext) -> torch.Tensor:
        prior = self.priors.get(context.view.name)
        if prior is None or prior.normal is None:
            return context.image.sum() * 0.0
        if self.normal_render == "composited":
            if context.normals is None:
                return context.image.sum() * 0.0
            return normal_loss(context.normals, prior.normal, prior.mask, self._edge_weights(context),
                               alpha=context.alpha[..., 0], confidence=prior.confidence)
        ids = self._median_ids(context, f"normal_render {self.normal_render!r}", "--normal-render composited")
        params = context.params
        if self.normal_render == "thin":
            thick, surface = median_surface_thinness(ids[0], params.quats, params.scales, context.view.viewmat,
                                                     prior.normal)
            return thinness_loss(thick, prior.normal, prior.mask & surface, self._edge_weights(context),
                                 confidence=prior.confidence)
        normals, surface = median_surface_normals(ids[0], params.means, params.quats, params.scales,
                                                  context.view.viewmat)
        return normal_loss(normals, prior.normal, prior.mask & surface, self._edge_weights(context),
                           confidence=prior.confidence)

    def _sky_term(self, context: LossContext) -> torch.Tensor:
        prior = self.priors.get(context.view.name)
        if prior is None or prior.sky is None or context.depth is None:
            return context.image.sum() * 0.0
        depth, alpha = context.depth[..., 0], context.alpha[..., 0]
        far = prior.far
        if far is None:
            # relative prior left unpinned: the farthest surface the Gaussians draw now
            surface = prior.mask & (alpha.detach() > 0.5) & (depth.detach() > 0)
            if not bool(surface.any()):
                return context.image.sum() * 0.0
            far = _far_depth(depth.detach(), surface)
        if far is None:
            return context.image.sum() * 0.0
        return sky_loss(depth, alpha, prior.sky, far)

    def _consistency_term(self, context: LossContext) -> torch.Tensor:
        if context.depth is None or context.normals is None:
            return context.image.sum() * 0.0
        mask = (context.alpha[..., 0] > 0.5)
        if context.mask is not None:
            mask = mask & context.mask[..., 0]
        return depth_normal_consistency_loss(context.depth[..., 0], context.normals, context.view.K.to(context.depth),
                                             mask=mask)


def _far_depth(depth: torch.Tensor, mask: torch.Tensor, quantile: float = 0.99) -> Optional[torch.Tensor]:
    """The view's far surface distance: a high quantile of its valid depths (robust to a few
    outliers), or None without any."""
    values = depth[mask & (depth > 0)]
    if values.numel() == 0:
        return None
    return torch.quantile(values.float(), quantile).to(depth.dtype)


def _failed_prediction(alignment: Any, max_error: float) -> bool:
    """True when the gate is on and the pinned prior contradicts the view's SfM points: its
    fit error is above ``max_error``, or the fit was refused as inverted or far off."""
    if max_error <= 0:
        return False
    if alignment.depth is None:
        return bool(alignment.contradicts)
    return alignment.median_error > max_error


def _alignment_summary(alignments: list, max_error: float = 0.0) -> str:
    """One line on how the relative depth priors were pinned to the SfM points (and which were dropped)."""
    fitted = [a for _, a in alignments if a.depth is not None]
    line = f"relative depth priors aligned to SfM points in {len(fitted)}/{len(alignments)} views"
    if fitted:
        points = sorted(a.points for a in fitted)[len(fitted) // 2]
        error = sorted(a.median_error for a in fitted)[len(fitted) // 2]
        line += f" (median {points} points, median fit error {error:.1%})"
    dropped = [(name, a) for name, a in alignments if _failed_prediction(a, max_error)]
    if dropped:
        line += (f"; {len(dropped)} view(s) train without priors, their prediction contradicts their SfM points "
                 f"(fit error above {max_error:.0%}, or inverted): "
                 + ", ".join(f"{name} ({'inverted' if a.scale <= 0 else f'{a.median_error:.0%}'})"
                             for name, a in dropped[:4])
                 + (f" and {len(dropped) - 4} more" if len(dropped) > 4 else ""))
        if len(dropped) == len(alignments):
            line += " (every view: the prior failed on this scene)"
    refused = [(name, a.reason) for name, a in alignments if a.depth is None and not _failed_prediction(a, max_error)]
    if refused:
        line += "; aligned to the rendered depth instead: " + "; ".join(f"{n}: {r}" for n, r in refused[:3])
        if len(refused) > 3:
            line += f"; and {len(refused) - 3} more"
    return line
