"""Depth and normal priors: the on-disk format, the sources, and the loss terms.

- :mod:`.io`: ``priors/<source>/`` maps (load, check, resize, write);
- :mod:`.sfm`: sparse depth from COLMAP points;
- :mod:`.losses`: edge-aware depth / normal / consistency losses used in training.

The sources themselves (which exist, what their files hold) are :class:`PriorSource`
(:mod:`esgs.core.formats.scene_dir`).
"""
from ..formats.scene_dir import PriorSource, image_stem
from .io import PriorMaps, available_prior_sources, load_prior_maps, prior_dir, write_prior_maps

__all__ = ["PriorMaps", "PriorSource", "available_prior_sources", "image_stem", "load_prior_maps", "prior_dir",
           "write_prior_maps"]
