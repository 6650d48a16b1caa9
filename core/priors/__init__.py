"""Depth and normal priors: the on-disk format, the sources, and the loss terms.

- :mod:`.io`: ``priors/<source>/`` maps (load, check, resize, write);
- :mod:`.sfm`: sparse depth from COLMAP points;
- :mod:`.losses`: edge-aware depth / normal / consistency losses used in training.
"""
from .io import PRIOR_SOURCES, PriorMaps, available_prior_sources, image_stem, load_prior_maps, prior_dir, write_prior_maps

__all__ = ["PRIOR_SOURCES", "PriorMaps", "available_prior_sources", "image_stem", "load_prior_maps", "prior_dir",
           "write_prior_maps"]
