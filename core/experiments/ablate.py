"""The paper's ablation studies on one scene (``esgs ablate``).

Three studies, every run at the same step count and seeds, each in its own folder
``OUT/runs/<variant>/seed<k>`` (variants shared between studies are trained once):

- **grid**: 3DGS; +depth; +normal; +depth+normal; +all (depth + normal + GPDFN, K = 3),
  with the priors of ``priors`` (default: the first of gt, labels, ndn, sfm in SCENE/priors);
- **priors**: the 3DGS baseline, then full ESGS with each prior source that exists (none =
  GPDFN only; gt last, the upper bound);
- **fused_k**: full ESGS with K = 1..5 fused Gaussians (K = 1 is GPDFN off).

Results: ``OUT/ablation.md`` and ``OUT/ablation.json`` (mean and std over seeds of SSIM,
PSNR, LPIPS and the mean and std of centre-to-mesh distances, opacity >= 0.5).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from ..errors import ConfigError, DatasetError
from ..formats.scene_dir import PriorSource, SceneDir, names
from .runs import RunTask
from .tables import QUALITY_COLUMNS, aggregate, markdown_table

#: Prior sources in the order of the paper's prior-source study: none first, then the least
#: faithful up to gt, the upper bound.
PRIOR_SOURCES = ("none", *names(tuple(reversed(PriorSource.standard_sources()))))
#: The studies, in the order of the tables.
STUDIES = ("grid", "priors", "fused_k")
#: Preference when no source is named.
DEFAULT_PRIOR_ORDER = names(PriorSource.standard_sources())


@dataclass(frozen=True)
class Variant:
    """One configuration of a study: ``key`` names its run folder, ``esgs`` its ESGSConfig values."""

    study: str
    label: str
    key: str
    esgs: tuple = ()

    def esgs_dict(self) -> dict[str, Any]:
        return dict(self.esgs)


def available_priors(scene: Path) -> dict[str, set[str]]:
    """Prior sources under SCENE/priors and which of depth/normal each provides."""
    found = {}
    for source in DEFAULT_PRIOR_ORDER:
        kinds = {kind for kind in ("depth", "normal") if SceneDir(scene).has_prior_maps(source, kind)}
        if kinds:
            found[source] = kinds
    return found


def _variant(study: str, label: str, *, source: str = "", depth: bool = False, normal: bool = False,
             fused_k: int = 0) -> Variant:
    parts = []
    if depth:
        parts.append("depth")
    if normal:
        parts.append("normal")
    if fused_k > 1:
        parts.append(f"gpdfn{fused_k}")
    uses_priors = depth or normal
    key = "-".join(parts) or "3dgs"
    if uses_priors:
        key += f"-{source}"
    esgs: dict[str, Any] = {"priors": source if uses_priors else "", "depth": depth, "normal": normal,
                            "gpdfn": fused_k > 1, "fused_k": max(fused_k, 1) if fused_k > 1 else 3}
    return Variant(study, label, key, tuple(sorted(esgs.items())))


def ablation_variants(scene: Path, priors: str = "", fused_ks: Sequence[int] = (1, 2, 3, 4, 5),
                      studies: Sequence[str] = STUDIES) -> list[Variant]:
    """Every (study, variant) of the chosen ``studies`` on ``scene``; see the module docstring."""
    unknown = [name for name in studies if name not in STUDIES]
    if unknown or not studies:
        raise ConfigError(f"unknown or no studies {', '.join(unknown)}".rstrip(), hint=f"choose among {', '.join(STUDIES)}")
    found = available_priors(scene)
    if priors and priors != "none" and priors not in found:
        raise DatasetError(f"no prior maps for source {priors!r} (depth/ or normal/)", path=SceneDir(scene).prior(priors),
                           hint=f"sources found: {', '.join(found) or 'none'}; make them with esgs priors")
    source = priors or next(iter(found), "")
    if priors == "none":
        source = ""
    kinds = found.get(source, set())
    depth, normal = "depth" in kinds, "normal" in kinds
    variants = [_variant("grid", "3DGS")]
    if depth:
        variants.append(_variant("grid", "+depth", source=source, depth=True))
    if normal:
        variants.append(_variant("grid", "+normal", source=source, normal=True))
    if depth and normal:
        variants.append(_variant("grid", "+depth+normal", source=source, depth=True, normal=True))
    variants.append(_variant("grid", "+all (depth+normal+GPDFN)" if kinds else "+GPDFN", source=source,
                             depth=depth, normal=normal, fused_k=3))
    variants.append(_variant("priors", "3DGS"))
    for name in PRIOR_SOURCES:
        if name == "none":
            variants.append(_variant("priors", "none", fused_k=3))
        elif name in found:
            variants.append(_variant("priors", name, source=name, depth="depth" in found[name],
                                     normal="normal" in found[name], fused_k=3))
    for k in fused_ks:
        if not 1 <= k <= 5:
            raise ConfigError(f"fused K must be in 1..5, got {k}")
        variants.append(_variant("fused_k", f"K={k}", source=source, depth=depth, normal=normal, fused_k=k))
    return [variant for variant in variants if variant.study in studies]


def plan_ablation(scene: Path, out: Path, *, iterations: int, seeds: Sequence[int], priors: str = "",
                  fused_ks: Sequence[int] = (1, 2, 3, 4, 5), train: Optional[dict] = None,
                  studies: Sequence[str] = STUDIES) -> tuple[list[Variant], list[RunTask]]:
    """The variants and the (deduplicated) run tasks of an ablation."""
    scene, out = Path(scene), Path(out)
    variants = ablation_variants(scene, priors, fused_ks, studies)
    mesh = SceneDir(scene).ground_truth_mesh
    tasks: dict[tuple[str, int], RunTask] = {}
    for variant in variants:
        for seed in seeds:
            if (variant.key, seed) in tasks:
                continue
            config = {**(train or {}), "iterations": iterations, "seed": seed, "method": "esgs",
                      "method_config": variant.esgs_dict()}
            tasks[(variant.key, seed)] = RunTask(name=f"{variant.key}/seed{seed}", scene=scene,
                                                 out=out / "runs" / variant.key / f"seed{seed}", config=config,
                                                 variant=variant.key, seed=seed, scene_name=scene.name,
                                                 mesh=mesh if mesh.is_file() else None, measure_render=False)
    return variants, list(tasks.values())


def ablation_table(variants: Sequence[Variant], summaries: dict[str, list[dict]]) -> dict[str, list[dict]]:
    """Rows per study: the variant's label with mean/std over seeds of each quality figure."""
    keys = [key for key, _, _ in QUALITY_COLUMNS]
    studies: dict[str, list[dict]] = {}
    for variant in variants:
        rows = aggregate(summaries.get(variant.key, []), keys)
        row = rows[0] if rows else {"seeds": [], **{key: {"mean": None, "std": None, "n": 0} for key in keys}}
        row.update({"variant": variant.label, "run": variant.key})
        studies.setdefault(variant.study, []).append(row)
    return studies


STUDY_TITLES = {"grid": "Ablation grid", "priors": "Prior sources", "fused_k": "Fused Gaussians (GPDFN K)"}


def run_ablation(scene: str | Path, out: str | Path, *, iterations: int = 3000, seeds: Sequence[int] = (0,),
                 priors: str = "", fused_ks: Sequence[int] = (1, 2, 3, 4, 5), train: Optional[dict] = None,
                 on_run: Optional[Callable[[RunTask, str], None]] = None, studies: Sequence[str] = STUDIES) -> dict:
    """Run (or finish) the ablation of ``scene`` into ``out``; returns the table (also written).

    Runs train in this process one after another; a finished run (summary.json) is not
    repeated, a failed one is reported in the table's ``failed`` list and the others go on.
    ``train``: further TrainConfig values for every run (width, threads, backend, lpips...);
    ``studies``: which of :data:`STUDIES` to run.
    """
    from ..io_utils import atomic_write_json, atomic_write_text
    from .runs import run_task

    scene, out = Path(scene), Path(out)
    if not SceneDir(scene).has_model():
        raise DatasetError("not a scene folder (no sparse/)", path=scene, hint="make one with esgs scene or esgs colmap")
    variants, tasks = plan_ablation(scene, out, iterations=iterations, seeds=seeds, priors=priors,
                                    fused_ks=fused_ks, train=train, studies=studies)
    summaries: dict[str, list[dict]] = {}
    failed = []
    for task in tasks:
        status = "skipped" if task.finished() else "trained"
        try:
            summary = run_task(task)
        except Exception as err:  # noqa: BLE001 - one bad run must not lose the others
            failed.append({"run": task.name, "error": f"{type(err).__name__}: {err}"})
            if on_run:
                on_run(task, "failed")
            continue
        summaries.setdefault(task.variant, []).append(summary)
        if on_run:
            on_run(task, status)
    studies = ablation_table(variants, summaries)
    table = {"scene": str(scene), "iterations": iterations, "seeds": list(seeds), "priors": priors or "auto",
             "studies": studies, "failed": failed}
    atomic_write_json(out / "ablation.json", table)
    atomic_write_text(out / "ablation.md", ablation_markdown(table))
    return table


def ablation_markdown(table: dict) -> str:
    lines = [f"# Ablation: {Path(table['scene']).name}", "",
             f"{table['iterations']} steps per run, seeds {', '.join(map(str, table['seeds']))}; "
             "mean ± std over seeds. Distances: Gaussian centres with opacity >= 0.5 to mesh/ground_truth.ply "
             "(scene units).", ""]
    for study, rows in table["studies"].items():
        lines += [f"## {STUDY_TITLES.get(study, study)}", "", markdown_table(rows, QUALITY_COLUMNS)]
    if table["failed"]:
        lines += ["## Failed runs", ""] + [f"- {item['run']}: {item['error']}" for item in table["failed"]] + [""]
    return "\n".join(lines)
