"""Settings of the ESGS method: the prior losses and GPDFN added to the 3DGS trainer."""
from __future__ import annotations

from dataclasses import dataclass, field

from ...errors import ConfigError
from .gpdfn_settings import GPDFNConfig

DEPTH_MODES = ("log", "inverse")
#: Which rendered depth the depth prior is compared with (docs/esgs.md, "Which depth the prior meets").
DEPTH_RENDERS = ("expected", "plane", "centre")
#: Which rendered normal the normal prior meets (docs/esgs.md, "Which normal the prior meets").
NORMAL_RENDERS = ("composited", "median", "thin")
ALIGNMENTS = ("sfm", "render")
#: Settings that act only through one part of the method: with that part off they cannot change
#: a run (:meth:`ESGSConfig.idle_settings`). The switches themselves (``depth``, ``gpdfn``,
#: ``fused_k`` ...) are never listed: they decide whether the part is on.
PART_SETTINGS = {
    "depth": ("depth_weight", "depth_mode", "depth_decay", "depth_incidence", "depth_robust", "depth_render"),
    "normal": ("normal_weight", "normal_render"),
    "consistency": ("consistency_weight", "consistency_start_step"),
    "gpdfn": ("gpdfn_hidden", "gpdfn_voxel_size", "gpdfn_max_shift_voxels", "gpdfn_lr", "gpdfn_every"),
}


@dataclass
class ESGSConfig(GPDFNConfig):
    """What ESGS adds to a 3DGS run: the settings of the ``esgs`` method.

    Each part is a switch, all off in a bare ``ESGSConfig()``; the full method (its parts
    chosen for the prior source) is :func:`esgs.core.methods.full_esgs`, its one definition.
    GPDFN's own settings (``fused_k``, ``gpdfn_*``) are inherited from
    :class:`~.gpdfn_settings.GPDFNConfig`. Step numbers are for a 30,000-step run and scale
    with the run's length, like every other schedule of the trainer.
    """

    priors: str = field(default="", metadata={"help": "prior source under SCENE/priors/ (gt, labels, ndn, sfm); empty = none"})
    depth: bool = field(default=False, metadata={"help": "depth-prior loss"})
    normal: bool = field(default=False, metadata={"help": "normal-prior loss"})
    consistency: bool = field(default=False, metadata={"help": "depth-normal consistency loss (needs no prior)"})
    gpdfn: bool = field(default=False, metadata={"help": "GPDFN neighbour fusion"})
    depth_weight: float = field(default=1.0, metadata={"help": "weight of the depth-prior loss (docs/esgs_acceptance.md: how it was chosen)"})
    normal_weight: float = field(default=0.02, metadata={
        "help": "weight of the normal-prior loss (0.02 for normal_render thin, chosen in docs/esgs.md 'Which normal "
                "the prior meets'; runs before it used 0.05 on the composited normal)"})
    consistency_weight: float = field(default=0.05, metadata={"help": "weight of the depth-normal consistency loss"})
    depth_mode: str = field(default="log", metadata={"help": "depth error space: log or inverse", "choices": DEPTH_MODES})
    depth_decay: float = field(default=1.0, metadata={
        "help": "the depth prior's weight at the run's last step, as a fraction of depth_weight, reached "
                "geometrically from the prior start step (0.1: ten times weaker at the end); 1 = constant"})
    depth_incidence: float = field(default=0.0, metadata={
        "help": "a prior depth from a surface estimate errs along the ray as 1/|cos| of the angle between the "
                "ray and the surface: depth-prior pixels whose prior normal meets the ray at |cos| below this "
                "weigh (cos / this)^2 (needs prior normals); 0 = off"})
    depth_robust: float = field(default=0.0, metadata={
        "help": "scale s of a robust depth error: a pixel's error e counts as s log(1 + e/s), so prior pixels "
                "that disagree with the render by much more than s pull less; 0 = plain L1"})
    depth_render: str = field(default="expected", metadata={
        "help": "the rendered depth the depth prior meets: expected = the weighted mean depth of every Gaussian "
                "a ray passes through; plane = where the ray meets the plane of the one Gaussian at which the "
                "pixel's transmittance crosses one half (its median surface); centre = that Gaussian's centre "
                "depth. plane and centre need the cpu or reference backend",
        "choices": DEPTH_RENDERS})
    normal_render: str = field(default="thin", metadata={
        "help": "the rendered normal the normal prior meets: composited = the blend of every Gaussian's normal "
                "along the ray (its gradient also moves and fades Gaussians to change the blend); median = the "
                "normal of the one Gaussian at which the pixel's transmittance crosses one half (the prior only "
                "turns that Gaussian, never moves it); thin = that Gaussian's variance along the prior normal over its "
                "mean variance (turns and flattens it, never moves it). median and thin need the cpu or reference "
                "backend",
        "choices": NORMAL_RENDERS})
    flatten_weight: float = field(default=0.0, metadata={
        "help": "weight of a flattening loss (the mean smallest scale over the scene extent) from the prior "
                "start step: flat Gaussians make the shortest axis, which the normal prior turns, a normal; "
                "0 = off"})
    relative_alignment: str = field(default="sfm", metadata={
        "help": "scale/shift of relative depth priors (NDN): sfm = fitted once to the SfM points each image "
                "observes, so the prior holds the surface's distance too (falls back to render per view when "
                "too few points); render = refitted to the rendered depth every step (shape only)",
        "choices": ALIGNMENTS})
    max_alignment_error: float = field(default=0.15, metadata={
        "help": "with relative_alignment sfm: a view whose relative depth prior, once pinned to its SfM points, "
                "still disagrees with them by more than this median relative error is taken as a failed "
                "prediction and trains without priors (depth and normal); 0 = keep every view"})
    prior_start_step: int = field(default=500, metadata={"help": "first step of the prior losses (of 30,000)"})
    consistency_start_step: int = field(default=7000, metadata={"help": "first step of the consistency loss (of 30,000)"})
    edge_strength: float = field(default=10.0, metadata={"help": "edge-aware weighting exp(-s |grad I|); 0 = uniform"})
    use_masks: bool = field(default=True, metadata={"help": "exclude sky/no-surface pixels from prior losses (the sky fix)"})
    sky_weight: float = field(default=0.3, metadata={
        "help": "weight of the sky loss: over pixels the prior marks as having no surface (sources whose "
                "mask_kind is surface: gt, ndn), Gaussians drawn nearer than the view's farthest surface are "
                "pushed beyond it (docs/esgs.md, 'The sky loss'); needs use_masks; 0 = off"})
    max_prior_depth: float = field(default=0.0, metadata={"help": "ignore prior depths beyond this (scene units; 0 = no limit)"})
    prior_points: int = field(default=0, metadata={
        "help": "Gaussians seeded per training view from the depth prior at the start, beside the SfM points: "
                "pixels inside the prior's mask (no sky) drawn in proportion to its confidence and lifted to "
                "their prior depth (docs/esgs.md, 'Gaussians seeded from the depth prior'); needs a metric "
                "depth prior; 0 = off"})

    def validate(self) -> None:
        if self.prior_points > 0 and not self.priors:
            raise ConfigError("prior_points seeds Gaussians from a depth prior, and there is no prior source",
                              hint="pass --priors auto|gt|labels|ndn|sfm, or --prior-points 0")
        if (self.depth or self.normal) and not self.priors:
            raise ConfigError("depth/normal prior losses need a prior source",
                              hint="pass --priors gt|labels|ndn|sfm (folders under SCENE/priors/)")
        if self.depth_mode not in DEPTH_MODES:
            raise ConfigError(f"depth_mode must be one of {DEPTH_MODES}, got {self.depth_mode!r}")
        if self.depth_render not in DEPTH_RENDERS:
            raise ConfigError(f"depth_render must be one of {DEPTH_RENDERS}, got {self.depth_render!r}")
        if self.normal_render not in NORMAL_RENDERS:
            raise ConfigError(f"normal_render must be one of {NORMAL_RENDERS}, got {self.normal_render!r}")
        if self.relative_alignment not in ALIGNMENTS:
            raise ConfigError(f"relative_alignment must be one of {ALIGNMENTS}, got {self.relative_alignment!r}")
        for name in ("depth_weight", "normal_weight", "consistency_weight", "edge_strength", "max_prior_depth",
                     "max_alignment_error", "sky_weight", "depth_robust", "flatten_weight", "depth_decay",
                     "depth_incidence", "prior_points"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)}")
        super().validate()

    def idle_settings(self) -> tuple[str, ...]:
        """Names of the settings that cannot change a run with these switches: those of the parts
        that are off (:data:`PART_SETTINGS`). A saved run that differs from a request only in
        them is the same run (the bench's and the studies' stale check)."""
        off = {"depth": not self.depth, "normal": not self.normal, "consistency": not self.consistency,
               "gpdfn": not self.gpdfn_on}
        return tuple(name for part, names in PART_SETTINGS.items() if off[part] for name in names)

    @property
    def gpdfn_on(self) -> bool:
        """GPDFN acts only when switched on and fusing more than the Gaussian itself."""
        return self.gpdfn and self.fused_k > 1

    @property
    def sky_loss_on(self) -> bool:
        """The sky loss acts only with a weight, a prior source to say where sky is, and masks honoured."""
        return self.sky_weight > 0 and bool(self.priors) and self.use_masks

    @property
    def seeds_on(self) -> bool:
        """Gaussians are seeded from the depth prior (``prior_points`` with a prior source)."""
        return self.prior_points > 0 and bool(self.priors)

    @property
    def loads_priors(self) -> bool:
        """The run reads ``SCENE/priors/<priors>``: for a prior loss, the sky loss or the seeds."""
        return self.depth or self.normal or self.sky_loss_on or self.seeds_on

    @property
    def enabled(self) -> bool:
        return self.depth or self.normal or self.consistency or self.gpdfn_on or self.sky_loss_on or self.seeds_on
