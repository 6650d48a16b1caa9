"""Settings of the comparison methods that run inside the trainer (Mip-Splatting, DropoutGS).

Torch-free, so CLI parsers can build flags without loading torch. Field names keep their
method's prefix (``mip_``, ``dropout_``): they are flat ``esgs train`` flags beside every
other method's.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ...errors import ConfigError


@dataclass
class MipSplattingConfig:
    """Settings of the ``mip-splatting`` method (Yu et al., CVPR 2024)."""

    mip_filter_3d: float = field(default=0.2, metadata={
        "help": "Mip-Splatting 3D filter: variance = this / (max sampling rate)^2, in units of the pixel footprint"})
    mip_filter_2d: float = field(default=0.1, metadata={
        "help": "Mip-Splatting 2D filter variance in pixels^2 (the rasterizer's antialiased mode)"})
    mip_frustum_margin: float = field(default=0.15, metadata={
        "help": "a Gaussian centre counts as seen by a camera within this fraction beyond the image border"})

    def validate(self) -> None:
        for name in ("mip_filter_3d", "mip_filter_2d", "mip_frustum_margin"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)}")


@dataclass
class DropoutGSConfig:
    """Settings of the ``dropout-gs`` method (Xu et al., CVPR 2025)."""

    dropout_rate: float = field(default=0.1, metadata={"help": "fraction of Gaussians dropped per training step"})
    dropout_compensate: bool = field(default=False, metadata={
        "help": "scale the kept opacities by 1 / (1 - rate) (DropGaussian's variant; DropoutGS does not)"})

    def validate(self) -> None:
        if not 0.0 <= self.dropout_rate < 1.0:
            raise ConfigError(f"dropout_rate must be in [0, 1), got {self.dropout_rate}",
                              hint="e.g. --dropout-rate 0.1 (the DropoutGS paper uses 0.1-0.2)")
