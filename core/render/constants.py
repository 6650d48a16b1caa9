"""Numbers every rasterizer backend must agree on (the semantics, not the code).

Both the CPU backend and the dense reference read these, so a change of cut-off moves
both at once and the equality tests keep meaning "same rendering rule".
"""
from __future__ import annotations

import math

#: A Gaussian whose alpha at a pixel is below this contributes nothing there.
ALPHA_MIN = 1.0 / 255.0
#: Alpha is clamped to this so that 1 - alpha never reaches zero (the backward divides by it).
ALPHA_MAX = 0.99
#: A pixel stops compositing before the Gaussian that would bring its transmittance below this.
TRANSMITTANCE_MIN = 1e-4
#: Screen-space dilation (pixels^2 added to the 2D covariance diagonal) of the classic mode.
CLASSIC_DILATION = 0.3
#: The projection Jacobian is evaluated with the image-plane position clamped to the image
#: widened by this fraction on each side, so that Gaussians far outside the view do not
#: get absurd first-order footprints (the same idea as 3DGS' 1.3 x tan(fov) limit).
JACOBIAN_MARGIN = 0.15
#: log(1 / ALPHA_MIN): opacity * exp(-q / 2) >= ALPHA_MIN  <=>  q <= 2 (log(opacity) + this).
LOG_INV_ALPHA_MIN = math.log(255.0)
#: Default near plane of :func:`~.api.rasterization`: centres nearer the camera than this are not drawn.
NEAR_PLANE = 0.01
#: Default far plane of :func:`~.api.rasterization`: in effect none.
FAR_PLANE = 1e10
