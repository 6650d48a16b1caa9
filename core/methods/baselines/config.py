"""Settings of the comparison methods that run inside the trainer (Mip-Splatting, DropoutGS, PGSR).

Torch-free, so CLI parsers can build flags without loading torch. Field names keep their
method's prefix (``mip_``, ``dropout_``, ``pgsr_``): they are flat ``esgs train`` flags beside every
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


@dataclass
class PGSRConfig:
    """Settings of the ``pgsr`` method (Chen et al., "PGSR: Planar-based Gaussian Splatting", TVCG 2024).

    Weights are the paper's; step counts are written for the 30,000-step schedule and scale
    with the run's length like every other schedule (docs/baselines.md, "PGSR").
    """

    pgsr_flatten_weight: float = field(default=100.0, metadata={
        "help": "weight of the flattening loss, mean over Gaussians of the smallest scale / scene extent (paper: 100)"})
    pgsr_single_view_weight: float = field(default=0.015, metadata={
        "help": "weight of the single-view depth-normal consistency loss (paper: 0.015)"})
    pgsr_single_view_from: int = field(default=7000, metadata={
        "help": "first step of the single-view loss, of 30,000 (scaled; paper: 7,000)"})
    pgsr_multi_view_geo_weight: float = field(default=0.03, metadata={
        "help": "weight of the multi-view forward-backward reprojection loss (paper: 0.03)"})
    pgsr_multi_view_ncc_weight: float = field(default=0.15, metadata={
        "help": "weight of the multi-view photometric NCC loss (paper: 0.15)"})
    pgsr_multi_view_from: int = field(default=7000, metadata={
        "help": "first step of both multi-view losses, of 30,000 (scaled; paper: 7,000)"})
    pgsr_multi_view_samples: int = field(default=4096, metadata={
        "help": "pixels sampled per step for the multi-view losses (paper: 102,400 on ~1.9 MP images)"})
    pgsr_patch_radius: int = field(default=3, metadata={
        "help": "NCC patch half-size in pixels: (2r + 1)^2 grey patches (paper: 3, 7x7 patches)"})
    pgsr_pixel_error_threshold: float = field(default=1.0, metadata={
        "help": "pixels whose forward-backward reprojection error is at least this (px) leave both multi-view "
                "losses (paper: 1)"})
    pgsr_neighbours: int = field(default=8, metadata={
        "help": "neighbouring training views kept per view, nearest camera centres first (paper: 8)"})
    pgsr_neighbour_max_angle_deg: float = field(default=30.0, metadata={
        "help": "a neighbour's viewing direction is within this angle of the view's (paper: 30 degrees)"})

    def validate(self) -> None:
        for name in ("pgsr_flatten_weight", "pgsr_single_view_weight", "pgsr_multi_view_geo_weight",
                     "pgsr_multi_view_ncc_weight", "pgsr_single_view_from", "pgsr_multi_view_from"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("pgsr_multi_view_samples", "pgsr_neighbours"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.pgsr_patch_radius < 0:
            raise ConfigError(f"pgsr_patch_radius must be >= 0, got {self.pgsr_patch_radius}")
        if self.pgsr_pixel_error_threshold <= 0:
            raise ConfigError(f"pgsr_pixel_error_threshold must be > 0, got {self.pgsr_pixel_error_threshold}")
        if not 0 < self.pgsr_neighbour_max_angle_deg <= 180:
            raise ConfigError(f"pgsr_neighbour_max_angle_deg must be in (0, 180], got "
                              f"{self.pgsr_neighbour_max_angle_deg}")


@dataclass
class ScaffoldGSConfig:
    """Settings of the ``scaffold-gs`` method (Lu et al., "Scaffold-GS: Structured 3D Gaussians for
    View-Adaptive Rendering", CVPR 2024).

    Sizes and thresholds are the paper's; step counts are written for the 30,000-step schedule and
    scale with the run's length like every other schedule (docs/baselines.md, "Scaffold-GS").
    """

    scaffold_feature_dim: int = field(default=32, metadata={
        "help": "length of each anchor's feature vector, also the MLPs' hidden width (paper: 32)"})
    scaffold_offsets: int = field(default=10, metadata={
        "help": "neural Gaussians (learned offsets) per anchor, k (paper: 10)"})
    scaffold_voxel_size: float = field(default=0.0, metadata={
        "help": "anchor voxel size in scene units; 0 = the median distance of the SfM points to their nearest "
                "neighbour (the paper's default)"})
    scaffold_volume_weight: float = field(default=0.01, metadata={
        "help": "weight of the volume regulariser, mean over the rendered neural Gaussians of the product of "
                "their scales (paper: 0.01)"})
    scaffold_grow_threshold: float = field(default=2e-4, metadata={
        "help": "mean screen-space gradient (NDC units, as the densification gradient threshold) above which a neural "
                "Gaussian asks for a new anchor at the coarsest level; x2 per finer level (paper: 2e-4)"})
    scaffold_grow_levels: int = field(default=3, metadata={
        "help": "voxel levels anchors grow on: 16, 4 and 1 voxel sizes for 3 levels (paper: 3)"})
    scaffold_prune_opacity: float = field(default=0.005, metadata={
        "help": "anchors whose neural Gaussians' summed opacity averages below this per view are pruned "
                "(paper: 0.005)"})
    scaffold_success_threshold: float = field(default=0.8, metadata={
        "help": "an anchor (a neural Gaussian: half of it) must have been in view for this fraction of the "
                "steps between two updates before it is grown from or pruned (paper: 0.8)"})
    scaffold_statistics_from: int = field(default=500, metadata={
        "help": "first step whose gradients and opacities count for growing and pruning, of 30,000 "
                "(scaled; paper: 500)"})
    scaffold_grow_from: int = field(default=1500, metadata={
        "help": "first anchor update (growing and pruning), of 30,000 (scaled; paper: 1,500); updates then "
                "follow the trainer's densification interval until the end of densification"})

    def validate(self) -> None:
        for name in ("scaffold_feature_dim", "scaffold_offsets", "scaffold_grow_levels"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("scaffold_voxel_size", "scaffold_volume_weight", "scaffold_grow_threshold",
                     "scaffold_prune_opacity", "scaffold_statistics_from", "scaffold_grow_from"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.scaffold_success_threshold <= 1.0:
            raise ConfigError(f"scaffold_success_threshold must be in [0, 1], got {self.scaffold_success_threshold}")
