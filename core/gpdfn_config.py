"""Settings of the GPDFN module (torch-free, so CLI parsers can build flags without loading torch)."""
from __future__ import annotations

from dataclasses import dataclass, field

from .errors import ConfigError


@dataclass
class GPDFNConfig:
    """Settings of the fusion module."""

    fused_k: int = field(default=3, metadata={"help": "Gaussians fused per Gaussian, itself included (1 = off; paper best: 3)"})
    hidden: int = field(default=16, metadata={"help": "width of the 1D convolutions"})
    voxel_size: float = field(default=0.0, metadata={"help": "voxel side in scene units (0 = automatic from Gaussian spacing)"})
    max_shift_voxels: float = field(default=1.0, metadata={"help": "largest learned correction of a sampling offset, in voxels"})
    lr: float = field(default=1e-3, metadata={"help": "Adam learning rate of the module's weights"})
    every: int = field(default=1, metadata={"help": "run GPDFN every k-th training step; the steps between add its "
                                                    "last residuals, detached (1 = every step, the paper's method)"})

    def validate(self) -> None:
        if not 1 <= self.fused_k <= 5:
            raise ConfigError(f"fused_k must be in 1..5 (the paper's Table 9 range), got {self.fused_k}")
        if self.hidden < 1:
            raise ConfigError(f"hidden must be positive, got {self.hidden}")
        if self.every < 1:
            raise ConfigError(f"every must be >= 1 (1 = GPDFN at every step), got {self.every}")
        if self.voxel_size < 0:
            raise ConfigError(f"voxel_size must be >= 0 (0 = automatic), got {self.voxel_size}")
