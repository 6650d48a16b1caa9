"""The main job end to end: synthetic Mars scene -> priors -> ESGS (and 3DGS) -> Blender -> report.

``run_demo(DemoConfig(...))`` runs every stage with progress and writes ``OUT/report.md``
(pictures beside it). Each stage's output lives in its own folder, so a re-run skips what is
already complete (scene, priors, runs) and redoes only the rest. The Blender stage runs the
bpy module in a child process (the ``"results_scene"`` job of :mod:`esgs.core.runtime`),
since core never imports bpy.

Prior sources (``DemoConfig.priors``): ``auto`` (the default, as for ``esgs train --esgs`` and
the Blender panel) fuses stereo labels, NDN and SfM depth per pixel with a confidence
(:mod:`esgs.core.priors.auto`, computed by the same priors job as ``esgs priors --method
auto``); ``ndn`` predicts dense relative depth and normals with the NDN weights shipped in
the package; ``sfm`` projects the scene's COLMAP points (sparse depth, no normals); ``gt``
uses the synthetic scene's exact maps (an upper bound). The ESGS run is
:func:`esgs.core.methods.full_esgs` of the source (:func:`esgs_settings`).
"""
from __future__ import annotations

import contextlib
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional


from ..errors import ConfigError, DatasetError, ESGSError
from ..progress import ProgressCallback, ProgressEvent, no_progress
from ..formats.scene_dir import PriorSource, SceneDir, names
from ..formats.run_dir import RunDir

if TYPE_CHECKING:
    from ..train import TrainConfig

#: Prior sources the demo can train ESGS with (folders under SCENE/priors/).
PRIOR_SOURCES = names(PriorSource.for_synthetic_scenes())
SPARSE_POINTS = ("triangulated", "exact")
#: The prior source of the demo's ESGS run unless --priors says otherwise: the default of
#: esgs.core.methods.full_esgs, esgs train --esgs and the Blender panel.
DEFAULT_PRIORS = PriorSource.AUTO.value


@dataclass
class DemoConfig:
    """Settings of the demo; the defaults needed about 9.5 CPU minutes with ndn priors (stages measured
    at 200 steps, README), plus the stereo labels the default auto priors compute (minutes)."""

    out: Path = field(default=Path("demo_output"), metadata={"help": "output folder (scene, runs, report)"})
    preset: str = field(default="cratered_plain", metadata={"help": "synthetic scene preset"})
    seed: int = field(default=1, metadata={"help": "scene seed"})
    views: int = field(default=12, metadata={"help": "camera views of the scene (every 8th is held out)"})
    width: int = field(default=320, metadata={"help": "image width in pixels"})
    height: int = field(default=180, metadata={"help": "image height in pixels"})
    samples: int = field(default=16, metadata={"help": "Cycles samples per pixel"})
    iterations: int = field(default=1500, metadata={"help": "training steps per method"})
    priors: str = field(default=DEFAULT_PRIORS, metadata={
        "help": "prior source for ESGS (auto: the best of stereo labels, NDN and SfM per pixel, with a "
                "confidence; ndn: dense relative depth and normals from the shipped NDN weights; "
                "sfm: sparse depth from the COLMAP points; gt: the synthetic scene's exact maps)",
        "choices": PRIOR_SOURCES})
    sparse_points: str = field(default="triangulated", metadata={
        "help": "the scene's SfM points: triangulated = SIFT matches of the rendered images with the known "
                "poses, as a real capture gives (sparse, noisy); exact = the generator's surface samples "
                "(flatter every method's geometry)", "choices": SPARSE_POINTS})
    baseline: bool = field(default=True, metadata={"help": "also train the 3DGS baseline for comparison"})
    gpdfn: bool = field(default=True, metadata={"help": "use GPDFN in the ESGS run"})
    max_gaussians: int = field(default=40_000, metadata={"help": "cap on Gaussians per run"})
    blender: bool = field(default=True, metadata={"help": "build results.blend and the heat-map picture with bpy"})
    snapshots: int = field(default=5, metadata={"help": "renders of one held-out view during training"})
    threads: int = field(default=0, metadata={"help": "CPU threads (0 = all)"})

    def validate(self) -> None:
        if self.views < 3:
            raise ConfigError(f"views must be at least 3, got {self.views}")
        if self.iterations < 10:
            raise ConfigError(f"iterations must be at least 10, got {self.iterations}")
        if self.width < 32 or self.height < 32:
            raise ConfigError(f"image size must be at least 32x32, got {self.width}x{self.height}")
        if self.sparse_points not in SPARSE_POINTS:
            raise ConfigError(f"sparse_points must be one of {', '.join(SPARSE_POINTS)}, got {self.sparse_points!r}")
        if self.priors not in PRIOR_SOURCES:
            raise ConfigError(f"priors must be one of {', '.join(PRIOR_SOURCES)}, got {self.priors!r}")


def esgs_settings(priors: str = DEFAULT_PRIORS, gpdfn: bool = True) -> dict:
    """The ``ESGSConfig`` of the demo's ESGS run for a prior source, as a dict: the full method
    exactly as :func:`esgs.core.methods.full_esgs` defines it (weights included), GPDFN optional.

    Every source drives the depth-prior loss (relative NDN depth is pinned to the scene's
    scale by a scale/shift fit to each image's SfM points, since the prior's EXR says
    ``relative``; auto's depth is weighted per pixel by its confidence).
    Sources with normals (auto, ndn, gt) also drive the normal-prior loss, the paper's full
    alignment branch; sparse ``sfm`` has no normals, so the depth-normal consistency loss
    stands in for them there.
    """
    from ..config import config_to_dict
    from ..methods import full_esgs

    if priors not in PRIOR_SOURCES:
        raise ConfigError(f"unknown prior source {priors!r}", hint=f"use one of {', '.join(PRIOR_SOURCES)}")
    return config_to_dict(full_esgs(priors, gpdfn=gpdfn))


def _esgs_settings_of(switches: dict) -> Any:
    """The ESGSConfig of the demo's switches (None for the 3DGS run, which has none)."""
    from ..config import config_from_dict
    from ..methods import ESGSConfig

    return config_from_dict(ESGSConfig, switches) if switches else None


class StageClock:
    """Wall and CPU seconds of the demo's stages (CPU includes finished child processes).

    CPU time is what an idle machine would need at one core per busy thread, so it is the
    figure to scale from when the machine is shared; wall time is what the user waited.
    """

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}
        self._started = self._now()

    @staticmethod
    def _now() -> tuple[float, float]:
        times = os.times()
        return time.perf_counter(), times.user + times.system + times.children_user + times.children_system

    def start(self) -> tuple[float, float]:
        return self._now()

    def stop(self, name: str, started: tuple[float, float]) -> None:
        wall, cpu = self._now()
        self.timings[f"{name}_s"] = wall - started[0]
        self.timings[f"{name}_cpu_s"] = cpu - started[1]

    def finish(self) -> dict[str, float]:
        self.stop("total", self._started)
        return dict(self.timings)


# --------------------------------------------------------------------------------------
def _run_stage(job: str, config: Any, stage: str, progress: ProgressCallback, log_path: Path) -> Any:
    """Run a registered child job for a demo stage, keep its output in a log; the child's
    error comes back as our error type, a crash with its last lines. Returns its result."""
    from ..runtime import ChildJob, child_command

    progress(ProgressEvent(step=0, total=1, stage=stage, kind="message", message=f"{stage}: {job} job"))
    log_path.parent.mkdir(parents=True, exist_ok=True)
    workdir = log_path.parent / f".{stage}_job"
    with open(log_path, "w", encoding="utf-8") as log:
        child = ChildJob(job, config, workdir=workdir, command=child_command(sys.executable),
                         on_output=lambda line: print(line, file=log, flush=True))
        child.task = f"{stage} stage"
        state = child.start().wait(poll_s=0.2)
    if state.status == "finished":
        return child.result
    if child.error is not None:
        raise child.error
    tail = log_path.read_text(encoding="utf-8", errors="replace").strip().splitlines()[-8:]
    raise ESGSError(f"the {stage} stage failed (exit {state.returncode}): " + " | ".join(tail),
                    path=log_path, hint="see the log for the whole output")


def make_scene(config: DemoConfig, progress: ProgressCallback) -> Path:
    """Render the synthetic scene (``OUT/scene``); with triangulated points, render it into
    ``OUT/scene_rendered`` and make ``OUT/scene`` from it with SfM points of its own images."""
    scene = config.out / "scene"
    if SceneDir(scene).provenance.is_file():
        progress(ProgressEvent(0, 1, "scene", kind="message", message=f"scene: reusing {scene}"))
        return scene
    rendered = scene if config.sparse_points == "exact" else config.out / "scene_rendered"
    if not SceneDir(rendered).provenance.is_file():
        from ..terrain.scene_job import SceneJob, check_request

        job = SceneJob(preset=config.preset, seed=config.seed, views=config.views, width=config.width,
                       height=config.height, samples=config.samples)
        check_request(job, rendered)  # bad settings or no bpy fail here, before Blender starts
        _run_stage("scene", {"job": job, "out": str(rendered)}, "scene", progress, config.out / "logs" / "scene.log")
    if config.sparse_points == "triangulated":
        from ..experiments.sfm_scene import make_sfm_scene

        try:
            record = make_sfm_scene(rendered, scene, progress=progress)
        except DatasetError as error:  # tiny or textureless renders: say so and go on with exact points
            progress(ProgressEvent(0, 1, "scene", kind="message",
                                   message=f"scene: no SfM points could be triangulated ({error}); using the "
                                           "generator's exact surface points instead"))
            os.replace(rendered, scene)  # a second run then reuses it like any finished scene
            return scene
        progress(ProgressEvent(0, 1, "scene", kind="message",
                               message=f"scene: {record['points']} SfM points triangulated from the images "
                                       f"(mean reprojection error {record['mean_reprojection_error_px']:.2f} px)"))
    return scene


def _priors_complete(scene: Path, source: str) -> bool:
    """Whether ``SCENE/priors/<source>/depth`` has a map for every image of the scene's COLMAP model."""
    from ..colmap import read_model

    folder = SceneDir(scene)
    if not folder.has_prior_maps(source, "depth"):
        return False
    images = [image.name for image in read_model(folder.model).images.values()]
    return bool(images) and all(folder.depth_map(source, name).is_file() for name in images)


def make_priors(config: DemoConfig, scene: Path, progress: ProgressCallback) -> None:
    """Write ``SCENE/priors/<config.priors>/`` unless complete (auto: the priors job of ``esgs
    priors --method auto``, which reuses its cache while the images hold; ndn: shipped NDN
    weights; sfm: COLMAP points)."""
    source = config.priors
    if source == "auto":
        from ..priors.job import PriorsSettings, compute_priors

        with _torch_threads(config.threads):  # its NDN step
            compute_priors(PriorsSettings(scene=scene, method=source), progress)
    elif _priors_complete(scene, source):
        progress(ProgressEvent(0, 1, "priors", kind="message", message=f"priors: reusing {SceneDir(scene).prior(source)}"))
        return
    elif source == "sfm":
        from ..colmap import read_model
        from ..priors.sfm import write_sfm_priors

        write_sfm_priors(scene, read_model(SceneDir(scene).model), progress=progress)
    elif source == "ndn":
        from ..ndn.infer import write_ndn_priors

        def relabel(event: ProgressEvent) -> None:
            progress(ProgressEvent(event.step, event.total, "ndn priors", dict(event.metrics), event.kind,
                                   event.message))

        with _torch_threads(config.threads):
            write_ndn_priors(scene, progress=relabel)  # the shipped weights, unless $ESGS_NDN_WEIGHTS names others
    if not _priors_complete(scene, source):
        raise ConfigError(f"the scene has no complete {source!r} priors", path=SceneDir(scene).prior(source),
                          hint="gt priors come with synthetic scenes from esgs scene; use --priors auto, ndn or sfm")


@contextlib.contextmanager
def _torch_threads(threads: int):
    """torch's CPU threads set to ``threads`` (0: left as they are) for the block."""
    import torch

    before = torch.get_num_threads()
    try:
        if threads > 0:
            torch.set_num_threads(threads)
        yield
    finally:
        torch.set_num_threads(before)


def _snapshot_hook(folder: Path, steps: list[int]):
    """A trainer hook rendering one held-out view at ``steps`` (the paper's Figure 17)."""
    import torch

    from ..formats.imageio import write_png
    from ..train.hooks import RunView, TrainHook

    class SnapshotHook(TrainHook):
        name = "demo_snapshots"

        def setup(self, run: RunView) -> None:
            self.view = (run.test_views or run.train_views)[0]

        def after_backward(self, run: RunView, context: Any) -> None:
            if context.step not in steps:
                return
            output = run.render_model(self.view, sh_degree=context.sh_degree)
            image = (output.image.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
            write_png(folder / f"step_{context.step:06d}.png", image)

    return SnapshotHook()


def train_method(config: DemoConfig, scene: Path, name: str, esgs: dict, progress: ProgressCallback,
                 snapshots: bool) -> dict:
    """Train one method into OUT/runs/<name> (skipped when already finished); returns its result.json."""
    from ..methods import train
    from ..train import TrainConfig

    run = config.out / "runs" / name
    train_config = TrainConfig(scene=scene, out=run, iterations=config.iterations, max_gaussians=config.max_gaussians,
                               threads=config.threads, resume=RunDir(run).has_checkpoints(),
                               method="esgs" if esgs else "3dgs", method_config=_esgs_settings_of(esgs),
                               progress_every=20)
    _check_same_settings(run, train_config)
    result_path = RunDir(run).result
    if result_path.is_file() and json.loads(result_path.read_text()).get("status") in ("completed", "time_limit") \
            and RunDir(run).metrics.is_file():
        progress(ProgressEvent(0, 1, name, kind="message", message=f"{name}: reusing finished run {run}"))
        return _run_summary(run)
    hooks = []
    if snapshots and config.snapshots > 0:
        steps = sorted({max(1, round(config.iterations * (i + 1) / config.snapshots)) for i in range(config.snapshots)})
        steps = sorted(set([min(50, config.iterations)] + steps))
        hooks.append(_snapshot_hook(config.out / "report" / "snapshots", steps))

    def relabel(event: ProgressEvent) -> None:
        progress(ProgressEvent(event.step, event.total, f"train {name}", dict(event.metrics), event.kind, event.message))

    train(train_config, progress=relabel, hooks=hooks)
    return _run_summary(run)


def _check_same_settings(run: Path, train_config: "TrainConfig") -> None:
    """Refuse to reuse or resume ``run`` when it was started with other settings than
    ``train_config`` (every setting that changes the result, today's defaults included).

    A finished run is reused and an unfinished one resumed; either would silently report
    (or mix) the old settings, e.g. after changing ``--priors`` in the same output folder, or
    after an update changed a default.
    """
    from dataclasses import replace

    from ..methods import get_method
    from ..train.trainer import changed_settings, describe_changes

    saved_path = RunDir(run).config
    if not saved_path.is_file():
        return
    try:
        saved = json.loads(saved_path.read_text())
    except (OSError, json.JSONDecodeError):
        return  # a damaged config: the trainer's own resume check reports it
    method = get_method(train_config.method)
    wanted = replace(train_config, method_config=method.settings_of(train_config))
    changed = changed_settings(wanted, saved, method)
    if changed:
        raise ConfigError(f"this folder holds a run started with other settings ({describe_changes(changed)})", path=run,
                          hint="choose another --out, or delete that run folder to train it again")


def _run_summary(run: Path) -> dict:
    """What the report needs of a finished run: its train_result.json plus metrics.json."""
    summary = json.loads(RunDir(run).result.read_text())
    metrics_path = RunDir(run).metrics
    summary["metrics"] = json.loads(metrics_path.read_text()) if metrics_path.is_file() else None
    return summary


def mesh_distances(scene: Path, run: Path, opacity_min: float = 0.5, threshold: float = 0.05) -> dict:
    """Gaussian-centre <-> ground-truth mesh statistics of a run (core only, no Blender).

    The demo calls it only for runs the Blender stage did not measure (the 3DGS baseline, or
    every run when Blender is off or failed); the Blender stage's ``compare.json`` holds the
    same statistics for the ESGS run.
    """
    from ..metrics.geometry import compare_ply_to_mesh

    result = compare_ply_to_mesh(RunDir(run).point_cloud, SceneDir(scene).ground_truth_mesh,
                                 opacity_min=opacity_min, threshold_m=threshold)
    return result.summary


def run_demo(config: DemoConfig, progress: ProgressCallback = no_progress) -> Path:
    """Run every stage and return the path of the report (``OUT/report.md``)."""
    from .report import write_report

    config.validate()
    config.out = Path(config.out).resolve()
    (config.out / "logs").mkdir(parents=True, exist_ok=True)
    clock = StageClock()

    started = clock.start()
    scene = make_scene(config, progress)
    clock.stop("scene", started)

    started = clock.start()
    make_priors(config, scene, progress)
    clock.stop("priors", started)

    runs: dict[str, dict] = {}
    folders = {"ESGS": "esgs", "3DGS": "3dgs"}
    started = clock.start()
    runs["ESGS"] = train_method(config, scene, "esgs", esgs_settings(config.priors, config.gpdfn), progress,
                                snapshots=True)
    clock.stop("esgs", started)
    if config.baseline:
        started = clock.start()
        runs["3DGS"] = train_method(config, scene, "3dgs", {}, progress, snapshots=False)
        clock.stop("3dgs", started)

    distances: dict[str, dict] = {}
    blender: Optional[dict] = None
    if config.blender:
        started = clock.start()
        request = {"scene": str(scene), "run": str(config.out / "runs" / "esgs"), "out": str(config.out / "blender")}
        try:
            _run_stage("results_scene", request, "blender", progress, config.out / "logs" / "blender.log")
            blender = json.loads((config.out / "blender" / "compare.json").read_text())
            blender["heat_map"] = str(config.out / "blender" / "heat_map.png")
            blender["blend"] = str(config.out / "blender" / "results.blend")
            # the heat map's comparison is the ESGS run's distance statistics: not measured twice
            distances["ESGS"] = blender
        except ESGSError as error:
            progress(ProgressEvent(0, 1, "blender", kind="message", message=f"warning: {error}"))
        clock.stop("blender", started)

    started = clock.start()
    for name in runs:
        if name not in distances:
            distances[name] = mesh_distances(scene, config.out / "runs" / folders[name])
    clock.stop("distances", started)

    timings = clock.finish()
    report = write_report(config, scene, runs, distances, blender, timings)
    progress(ProgressEvent(1, 1, "demo", kind="done", message=str(report)))
    return report
