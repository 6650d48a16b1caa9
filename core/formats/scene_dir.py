"""The scene folder (SCENE/ of DESIGN.md and docs/data.md) and the prior sources in it.

One owner for every name: :class:`PriorSource` lists the sources of ``priors/<source>/`` and
what each one's files are like, and :class:`SceneDir` spells every path of a scene folder::

    SCENE/
      images/                       RGB images, names as in the COLMAP model
      sparse/0/                     the COLMAP model (cameras, images, points3D)
      sparse_sfm/0/                 optional: pycolmap SfM on the renders of a synthetic scene
      priors/<source>/              depth/<stem>.exr, normal/<stem>.exr, mask/<stem>.png
      priors/labels/labels.json     how the label maps were made (per view statistics)
      priors/labels/accuracy.json   labels against priors/gt (synthetic scenes)
      mesh/ground_truth.ply         the true surface (synthetic scenes)
      mesh/reconstructed.ply        a mesh rebuilt from the images (``esgs labels --reconstruct``),
                                    with reconstructed.json (its report) and reconstructed_gaps.ply
      scene.json                    provenance: generator config and seed, units, frames, source

This module sits in the lowest layer (file formats): it imports only the standard library and
:mod:`.errors`, so the training layer can ask it which mask to use.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from ..errors import ConfigError


class PriorSource(str, Enum):
    """A source of prior maps, the ``<source>`` of ``SCENE/priors/<source>/``.

    The members are in order of preference (most faithful first): ``auto`` choices try them in
    this order. Being a ``str``, a member is its plain name in JSON, on the command line and in
    paths (``PriorSource.GT == "gt"``).
    """

    #: exact depth, normals and sky mask rendered with the synthetic scene (``esgs scene``)
    GT = "gt"
    #: depth and normals rendered from a mesh (the true one or a reconstructed one, ``esgs labels``)
    LABELS = "labels"
    #: dense relative depth and normals from the NDN diffusion network (``esgs priors --method ndn``)
    NDN = "ndn"
    #: sparse metric depth projected from the COLMAP points (``esgs priors --method sfm``)
    SFM = "sfm"
    #: the best prior the images allow, fused per pixel from labels, ndn and sfm with a confidence
    #: map and the sky of the best surface mask (``esgs priors --method auto``, :mod:`esgs.core.priors.auto`)
    AUTO = "auto"
    #: an experiment's source, not a product's: gt with the sky filled the way dense predictors
    #: fill it (:mod:`esgs.core.experiments.sky`)
    GT_SKYFILLED = "gt_skyfilled"

    def __str__(self) -> str:
        # the plain name in f-strings and messages, as the old string constants printed
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)

    @property
    def standard(self) -> bool:
        """One of the sources of the folder conventions (gt, labels, ndn, sfm); False for experiments'."""
        return self is not PriorSource.GT_SKYFILLED

    @property
    def has_mask(self) -> bool:
        """Whether the source writes ``mask/<stem>.png`` (every source does; what its zeros mean differs)."""
        return True

    @property
    def mask_kind(self) -> str:
        """What 0 in the mask means: ``"surface"`` (no surface along the ray: sky) or ``"coverage"``
        (only "no value here": sparse points, holes a mesh does not cover). The EXR header
        ``mask_kind`` says it per file; this is the fallback for files written before the header."""
        # auto's mask is coverage; it carries its sky in a sky/ folder of its own
        return "surface" if self in (PriorSource.GT, PriorSource.NDN, PriorSource.GT_SKYFILLED) else "coverage"

    @property
    def masks_sky(self) -> bool:
        """Whether the mask's zeros are sky (``mask_kind == "surface"``)."""
        return self.mask_kind == "surface"

    @property
    def dense_mask(self) -> bool:
        """Whether the mask covers the image densely, so it may mask the photometric loss. SfM's
        marks only the pixels that have a depth sample: it would blank most of the image; auto's
        holds SfM samples where no dense source reached."""
        return self not in (PriorSource.SFM, PriorSource.AUTO)

    @property
    def has_normals(self) -> bool:
        """Whether the source writes ``normal/<stem>.exr`` (SfM points carry no normals)."""
        return self is not PriorSource.SFM

    @property
    def relative_depth(self) -> bool:
        """Whether its depth is known only up to scale and shift (aligned during training)."""
        return self is PriorSource.NDN

    @property
    def depth_kind(self) -> str:
        """The EXR header ``depth_kind``: ``"relative"`` or ``"metric"`` (scene units)."""
        return "relative" if self.relative_depth else "metric"

    @property
    def computed_by_priors(self) -> bool:
        """Whether ``esgs priors --method <source>`` computes it for any scene."""
        return self in (PriorSource.NDN, PriorSource.SFM, PriorSource.AUTO)

    @property
    def made_by_labels(self) -> bool:
        """Whether ``esgs labels`` (rendering a mesh in Blender) writes it."""
        return self is PriorSource.LABELS

    @property
    def made_by_scene(self) -> bool:
        """Whether only the synthetic scene generator (``esgs scene``) can write it."""
        return self is PriorSource.GT

    @property
    def fused(self) -> bool:
        """Whether the source is built from the others (auto), not measured or predicted itself."""
        return self is PriorSource.AUTO

    @classmethod
    def standard_sources(cls) -> tuple["PriorSource", ...]:
        """gt, labels, ndn, sfm, auto: the folder conventions' sources, most faithful first (auto,
        made from labels, ndn and sfm, last: it is only as faithful as they are per pixel)."""
        return tuple(source for source in cls if source.standard)

    @classmethod
    def single_sources(cls) -> tuple["PriorSource", ...]:
        """gt, labels, ndn, sfm: the standard sources that are not fused from others."""
        return tuple(source for source in cls.standard_sources() if not source.fused)

    @classmethod
    def computed(cls) -> tuple["PriorSource", ...]:
        """The sources ``esgs priors`` can compute (its ``--method`` choices)."""
        return tuple(source for source in cls if source.computed_by_priors)

    @classmethod
    def for_synthetic_scenes(cls) -> tuple["PriorSource", ...]:
        """What a run on a synthetic scene can train with without a mesh step: the computed
        sources, then those the generator ships (ndn, sfm, gt)."""
        return (*cls.computed(), *(source for source in cls.standard_sources() if source.made_by_scene))

    @classmethod
    def auto_mask_order(cls) -> tuple["PriorSource", ...]:
        """The sources whose masks ``--mask-source auto`` tries, in this order (dense masks only)."""
        return tuple(source for source in cls.standard_sources() if source.dense_mask)

    @classmethod
    def parse(cls, name: str, choices: tuple["PriorSource", ...] | None = None) -> "PriorSource":
        """The member called ``name``; :class:`ConfigError` naming the ``choices`` (default: the
        standard sources) when it is none of them."""
        allowed = cls.standard_sources() if choices is None else choices
        for source in allowed:
            if source.value == name:
                return source
        raise ConfigError(f"unknown prior source {name!r}", hint=f"use one of {', '.join(map(str, allowed))}")


def names(sources: tuple[PriorSource, ...]) -> tuple[str, ...]:
    """The plain names of ``sources`` (argparse choices, JSON, old tuple constants)."""
    return tuple(source.value for source in sources)


def image_stem(image_name: str) -> str:
    """The image name without its extension, sub-folders kept ("a/b.png" -> "a/b")."""
    path = Path(image_name)
    return str(path.with_suffix("")) if path.suffix else image_name


#: names inside a scene folder, spelled once (SceneDir's properties join them to a root)
IMAGES = "images"
SPARSE = "sparse"
SPARSE_SFM = "sparse_sfm"
MODEL_INDEX = "0"
PRIORS = "priors"
MESH = "mesh"
GROUND_TRUTH_MESH = "ground_truth.ply"
RECONSTRUCTED_MESH = "reconstructed.ply"
SCENE_JSON = "scene.json"
LABELS_REPORT = "labels.json"
LABELS_ACCURACY = "accuracy.json"
PRIOR_KINDS = ("depth", "normal", "mask", "confidence", "sky", "second_depth")


@dataclass(frozen=True)
class SceneDir:
    """The files of one scene folder under ``root`` (module docstring)."""

    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @property
    def images(self) -> Path:
        """``images/``: the RGB images, named as in the COLMAP model."""
        return self.root / IMAGES

    def image(self, name: str) -> Path:
        """``images/<name>`` (``name`` as the COLMAP model spells it, sub-folders included)."""
        return self.images / name

    @property
    def sparse(self) -> Path:
        """``sparse/``: the folder of COLMAP models."""
        return self.root / SPARSE

    @property
    def model(self) -> Path:
        """``sparse/0``: the COLMAP model the scene is trained with."""
        return self.sparse / MODEL_INDEX

    @property
    def sfm_model(self) -> Path:
        """``sparse_sfm/0``: pycolmap SfM on a synthetic scene's renders (optional)."""
        return self.root / SPARSE_SFM / MODEL_INDEX

    @property
    def priors(self) -> Path:
        """``priors/``: one folder per prior source."""
        return self.root / PRIORS

    def prior(self, source: str) -> Path:
        """``priors/<source>``."""
        return self.priors / str(source)

    def prior_maps(self, source: str, kind: str) -> Path:
        """``priors/<source>/<kind>`` for kind depth, normal or mask."""
        if kind not in PRIOR_KINDS:
            raise ValueError(f"prior map kind must be one of {PRIOR_KINDS}, got {kind!r}")
        return self.prior(source) / kind

    def depth_map(self, source: str, image_name: str) -> Path:
        """``priors/<source>/depth/<stem>.exr`` of image ``image_name``."""
        return self.prior_maps(source, "depth") / f"{image_stem(image_name)}.exr"

    def normal_map(self, source: str, image_name: str) -> Path:
        """``priors/<source>/normal/<stem>.exr`` of image ``image_name``."""
        return self.prior_maps(source, "normal") / f"{image_stem(image_name)}.exr"

    def mask_map(self, source: str, image_name: str) -> Path:
        """``priors/<source>/mask/<stem>.png`` of image ``image_name``."""
        return self.prior_maps(source, "mask") / f"{image_stem(image_name)}.png"

    def confidence_map(self, source: str, image_name: str) -> Path:
        """``priors/<source>/confidence/<stem>.exr``: per-pixel trust in [0, 1] (optional; auto writes it)."""
        return self.prior_maps(source, "confidence") / f"{image_stem(image_name)}.exr"

    def second_depth_map(self, source: str, image_name: str) -> Path:
        """``priors/<source>/second_depth/<stem>.exr``: a second, independent depth estimate
        (optional; ``ndn`` writes its normals network's own depth there)."""
        return self.prior_maps(source, "second_depth") / f"{image_stem(image_name)}.exr"

    def sky_map(self, source: str, image_name: str) -> Path:
        """``priors/<source>/sky/<stem>.png``: 255 = no surface along the ray (optional; auto writes it)."""
        return self.prior_maps(source, "sky") / f"{image_stem(image_name)}.png"

    @property
    def labels_report(self) -> Path:
        """``priors/labels/labels.json``: how the label maps were made."""
        return self.prior(PriorSource.LABELS) / LABELS_REPORT

    @property
    def labels_accuracy(self) -> Path:
        """``priors/labels/accuracy.json``: the labels measured against ``priors/gt``."""
        return self.prior(PriorSource.LABELS) / LABELS_ACCURACY

    @property
    def mesh(self) -> Path:
        """``mesh/``."""
        return self.root / MESH

    @property
    def ground_truth_mesh(self) -> Path:
        """``mesh/ground_truth.ply``: the true surface of a synthetic scene (cameras' frame and units)."""
        return self.mesh / GROUND_TRUTH_MESH

    @property
    def reconstructed_mesh(self) -> Path:
        """``mesh/reconstructed.ply``: the mesh ``esgs labels --reconstruct`` rebuilds from the images."""
        return self.mesh / RECONSTRUCTED_MESH

    @property
    def reconstruction_report(self) -> Path:
        """``mesh/reconstructed.json``: the report of that reconstruction."""
        return self.reconstructed_mesh.with_suffix(".json")

    @property
    def reconstructed_gaps(self) -> Path:
        """``mesh/reconstructed_gaps.ply``: the triangles bridging gaps of the reconstructed mesh."""
        return gap_mesh_path(self.reconstructed_mesh)

    @property
    def provenance(self) -> Path:
        """``scene.json``: generator config and seed, units, frames, source."""
        return self.root / SCENE_JSON

    def has_model(self) -> bool:
        """Whether ``sparse/`` exists (what a complete scene folder has; writers make it last)."""
        return self.sparse.is_dir()

    def has_prior_maps(self, source: str, kind: str) -> bool:
        """Whether ``priors/<source>/<kind>`` is a folder."""
        return self.prior_maps(source, kind).is_dir()


def gap_mesh_path(mesh_path: str | Path) -> Path:
    """The gap mesh written beside a reconstructed mesh: ``<stem>_gaps.ply``."""
    mesh_path = Path(mesh_path)
    return mesh_path.with_name(f"{mesh_path.stem}_gaps.ply")
