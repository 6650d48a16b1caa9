"""Making a relative (or badly scaled) depth map metric against sparse or dense metric samples.

One owner of "pin a depth map to evidence": ``priors/auto`` pins relative NDN depth to each
view's SfM points, and ``write_ndn_priors`` pins an evidence network's metric depth to the
view's stereo labels. Both use the trainer's robust scale/shift fit
(:func:`.losses.fit_scale_shift`). Kept apart from :mod:`.auto` so the NDN writer can use it
without importing the module that runs it.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

#: Fewer samples than this and a fit (or a check against the samples) says nothing.
MIN_PIN_SAMPLES = 20


def pin_relative_depth(relative: np.ndarray, valid: np.ndarray, sfm_depth: np.ndarray) -> Optional[np.ndarray]:
    """A relative depth map made metric by a robust scale and shift fitted to the metric samples
    ``sfm_depth`` (> 0 where known; SfM points or stereo labels) over ``valid``; None with fewer
    than :data:`MIN_PIN_SAMPLES` samples or a scale that is not positive (the prediction inverts
    near and far)."""
    import torch  # here: the add-on imports priors modules in Blender's Python, which has no torch

    from .losses import fit_scale_shift

    check = valid & (sfm_depth > 0) & (relative > 0)
    if int(check.sum()) < MIN_PIN_SAMPLES:
        return None
    scale, shift = fit_scale_shift(torch.from_numpy(relative[check].astype(np.float64)),
                                   torch.from_numpy(sfm_depth[check].astype(np.float64)),
                                   torch.ones(int(check.sum()), dtype=torch.bool))
    if float(scale) <= 0:
        return None
    pinned = (float(scale) * relative.astype(np.float64) + float(shift)).astype(np.float32)
    return np.where(valid & (relative > 0) & (pinned > 0), pinned, 0.0).astype(np.float32)
