"""Settings of the GPDFN module: the one place they are defined (torch-free, so CLI parsers
can build flags without loading torch).

:class:`~.config.ESGSConfig` inherits these fields, so they are flags of ``esgs train``
(``--fused-k``, ``--gpdfn-voxel-size`` ...) and keys of a run's ``method_config`` without a
second copy; :class:`~.gpdfn.GPDFN` takes any object with them (an ESGSConfig included).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ...errors import ConfigError


@dataclass
class GPDFNConfig:
    """Settings of the fusion module."""

    fused_k: int = field(default=3, metadata={"help": "Gaussians fused by GPDFN per Gaussian, itself included "
                                                      "(1 = off; the paper's best: 3; range 1..5)"})
    gpdfn_hidden: int = field(default=8, metadata={
        "help": "width of GPDFN's 1D convolutions (saved with the run; 8 measured as good as 16 and 5-11 %% "
                "cheaper per full-ESGS CPU step, docs/esgs.md 'GPDFN's width')"})
    gpdfn_voxel_size: float = field(default=0.0, metadata={
        "help": "GPDFN voxel side in scene units (0 = automatic from the Gaussians' spacing)"})
    gpdfn_max_shift_voxels: float = field(default=1.0, metadata={
        "help": "largest learned correction of a GPDFN sampling offset, in voxels"})
    gpdfn_lr: float = field(default=1e-3, metadata={"help": "learning rate (Adam) of the GPDFN weights"})
    gpdfn_every: int = field(default=1, metadata={
        "help": "run GPDFN every k-th training step; the steps between add its last residuals, detached "
                "(1 = every step, the paper's method; docs/esgs.md)"})

    def validate(self) -> None:
        if not 1 <= self.fused_k <= 5:
            raise ConfigError(f"fused_k must be in 1..5 (the paper's Table 9 range), got {self.fused_k}")
        if self.gpdfn_hidden < 1:
            raise ConfigError(f"gpdfn_hidden must be positive, got {self.gpdfn_hidden}")
        if self.gpdfn_every < 1:
            raise ConfigError(f"gpdfn_every must be >= 1 (1 = GPDFN at every step), got {self.gpdfn_every}")
        if self.gpdfn_voxel_size < 0:
            raise ConfigError(f"gpdfn_voxel_size must be >= 0 (0 = automatic), got {self.gpdfn_voxel_size}")
        if self.gpdfn_max_shift_voxels < 0:
            raise ConfigError(f"gpdfn_max_shift_voxels must be >= 0, got {self.gpdfn_max_shift_voxels}")
