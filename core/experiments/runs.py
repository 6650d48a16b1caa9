"""One experiment run: train a TrainConfig in its own folder, then measure it.

A finished run leaves ``RUN/summary.json`` (written last, atomically); a task whose summary
exists is not trained again, and an interrupted one resumes from its newest checkpoint, as
long as the run folder's ``config.json`` holds the settings the task asks for now. A run
made with other settings (a changed default, another prior source) is stale: it is moved
aside to ``RUN.stale-<time>`` (kept, never deleted) and trained again.
"""
from __future__ import annotations

import json
import resource
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

SUMMARY_NAME = "summary.json"
def effective_settings(config: dict[str, Any]) -> dict[str, Any]:
    """``config`` (a TrainConfig dict of today's layout, ``method_config`` complete) with a
    method that adds nothing counted as plain 3DGS, whose settings cannot change the result
    (an ESGS run with every part off does not depend on the ESGS depth weight), an ESGS
    run's settings of its switched-off parts at their defaults, and a run without the sky
    model stripped of that model's settings (``SKY_MODEL_SETTINGS``)."""
    from ..train.config import SKY_MODEL_SETTINGS

    settings = dict(config)
    if settings.get("sky", "envmap") != "envmap":  # no sky model: its settings cannot act
        for name in SKY_MODEL_SETTINGS:
            settings.pop(name, None)
    method, method_config = settings.get("method", "3dgs"), settings.get("method_config")
    adds_nothing = (method == "esgs" and isinstance(method_config, dict) and not _esgs_enabled(method_config)) or \
        (method == "dropout-gs" and isinstance(method_config, dict) and not method_config.get("dropout_rate"))
    if method == "3dgs" or adds_nothing:
        settings["method"], settings["method_config"] = "3dgs", None
    elif method == "esgs" and isinstance(method_config, dict):
        settings["method_config"] = _without_idle_esgs_settings(method_config)
    return settings


def _without_idle_esgs_settings(method_config: dict[str, Any]) -> dict[str, Any]:
    """``method_config`` with the settings of its switched-off parts at their defaults
    (:meth:`ESGSConfig.idle_settings`): a depth-only run does not depend on the normal prior's form."""
    from ..methods import ESGSConfig

    try:
        idle = ESGSConfig(**method_config).idle_settings()
    except TypeError:  # unknown keys: compare as they are
        return method_config
    defaults = ESGSConfig()
    return {**method_config, **{name: getattr(defaults, name) for name in idle if name in method_config}}


def _esgs_enabled(method_config: dict[str, Any]) -> bool:
    from ..methods import ESGSConfig

    try:
        return ESGSConfig(**method_config).enabled
    except TypeError:  # unknown keys: not comparable, so not "off"
        return True


def _complete(config: dict[str, Any]) -> dict[str, Any]:
    """``config`` in today's layout with its method's settings complete (defaults filled in),
    the top-level settings left as they are (missing ones stay missing)."""
    from ..config import config_to_dict
    from ..errors import ConfigError
    from ..methods import get_method
    from ..train.config import TrainConfig, with_predating_values

    config = with_predating_values(config)
    try:
        method = get_method(config.get("method", "3dgs"))
        settings = method.settings_of(TrainConfig(method=method.name, method_config=config.get("method_config")))
    except ConfigError:
        return config
    return {**config, "method_config": config_to_dict(settings) if settings is not None else None}


@dataclass
class RunTask:
    """A training run of an experiment.

    ``config``: the TrainConfig as a dict (``config_to_dict`` form; ``scene`` and ``out``
    are set from the task); ``variant``/``seed``/``scene_name``: the labels of the
    tables; ``mesh``: ground-truth mesh for the distance figures (None = skip them).
    """

    name: str
    scene: Path
    out: Path
    config: dict[str, Any]
    variant: str = ""
    seed: int = 0
    scene_name: str = ""
    mesh: Optional[Path] = None
    measure_render: bool = True

    @property
    def summary_path(self) -> Path:
        return Path(self.out) / SUMMARY_NAME

    def finished(self) -> bool:
        """True when the run's summary exists and its saved settings are the task's."""
        return self.summary_path.is_file() and not self.stale_settings()

    def stale_settings(self) -> list[str]:
        """Names of the settings (those that change what is computed, see
        :func:`effective_settings`) whose value in the run folder's ``config.json`` differs from
        what the task asks for now; [] when they agree or the folder has no config yet.

        ``scene`` counts by its folder name: a run made on another scene folder (the bench's
        triangulated ``..._sfm`` copy in place of the generator's points) is another run,
        while a moved bench folder keeps its runs."""
        from ..config import config_to_dict
        from ..methods import train_config_from_dict
        from ..formats.run_dir import RunDir
        from ..train.trainer import RESUMABLE_SETTINGS
        from .executor import SCRATCH_PREFIX

        saved_path = RunDir(self.out).config
        if not saved_path.is_file():
            return []
        try:
            saved = json.loads(saved_path.read_text())
        except (OSError, ValueError):
            return [saved_path.name]  # unreadable: treat as made with other settings
        wanted = config_to_dict(train_config_from_dict({**self.config, "scene": str(self.scene),
                                                        "out": str(self.out), "resume": True}, saved=False))
        # a setting newer than the saved run counts with the value such runs had (PREDATING_VALUES)
        saved = effective_settings({**{name: None for name in wanted}, **_complete(saved)})
        wanted = effective_settings(json.loads(json.dumps(wanted)))
        stale = [name for name, value in wanted.items() if name not in RESUMABLE_SETTINGS and value != saved.get(name)]
        saved_scene = Path(str(saved.get("scene") or ""))
        # runs shipped to another Ray node before scratch copies kept the scene's name trained on "<scratch>/scene"
        unknown = saved_scene.name == "scene" and saved_scene.parent.name.startswith(SCRATCH_PREFIX)
        if saved_scene.name and not unknown and saved_scene.name != Path(self.scene).name:
            stale.append("scene")
        return sorted(stale)

    def set_aside_if_stale(self) -> Optional[Path]:
        """Move a stale run folder (see :meth:`stale_settings`) to ``OUT.stale-<UTC time>`` so the
        task trains afresh; returns the new place, or None when the folder is current or absent."""
        if not self.stale_settings():
            return None
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        target = Path(self.out).with_name(f"{Path(self.out).name}.stale-{stamp}")
        counter = 1
        while target.exists():
            target = Path(self.out).with_name(f"{Path(self.out).name}.stale-{stamp}-{counter}")
            counter += 1
        Path(self.out).rename(target)
        return target

    def load_summary(self) -> dict:
        return json.loads(self.summary_path.read_text())


def peak_memory_mib() -> float:
    """Peak resident memory of this process so far, MiB (ru_maxrss is KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def geometry_figures(point_cloud: Path, mesh: Path, *, opacity_min: float = 0.5,
                     surface_samples: int = 20_000) -> dict[str, Any]:
    """Mean and std of the distances from the centres (opacity >= ``opacity_min``) to ``mesh``."""
    from ..metrics.geometry import compare_ply_to_mesh

    summary = compare_ply_to_mesh(point_cloud, mesh, opacity_min=opacity_min, n_surface_samples=surface_samples).summary
    filtered = summary["gaussians_to_mesh_filtered"]
    return {"distance_mean": filtered["mean"], "distance_std": filtered["std"],
            "distance_count": filtered["count"], "fscore": summary["fscore"]}


def render_seconds_per_frame(run_dir: Path) -> Optional[float]:
    """Mean wall time of rendering each held-out view (training views if none) of a finished run."""
    import torch

    from ..methods import render_options
    from ..train.evaluate import load_run, load_run_sky
    from ..train.rendering import render_view

    config, data, model, backend, device = load_run(run_dir)
    render = render_options(config)
    sky = load_run_sky(run_dir, device)
    views = data.test or data.train
    if not views:
        return None
    background = torch.tensor(config.background, dtype=torch.float32, device=device)
    with torch.no_grad():
        params = model.render_params(model.max_sh_degree)
        times = []
        for view in views:
            start = time.perf_counter()
            render_view(params, view.viewmat.to(device), view.K.to(device), view.width, view.height,
                        background=background, backend=backend, num_threads=config.threads or None,
                        antialiased=render.antialiased, eps2d=render.eps2d, sky=sky)
            if device.type == "cuda":
                torch.cuda.synchronize()
            times.append(time.perf_counter() - start)
    return float(sum(times) / len(times))


def run_task(task: RunTask) -> dict[str, Any]:
    """Train ``task`` (or resume it), measure it and write its summary; returns the summary.

    A finished task (summary present) returns its stored summary without training.
    """
    from ..io_utils import atomic_write_json
    from ..methods import train, train_config_from_dict

    task.set_aside_if_stale()
    if task.finished():
        return {**task.load_summary(), "skipped": True}
    values = {**task.config, "scene": str(task.scene), "out": str(task.out), "resume": True}
    config = train_config_from_dict(values, saved=False)
    started = time.perf_counter()
    result = train(config)
    wall_s = time.perf_counter() - started
    # a time budget (max_minutes) ends a run early on purpose: that run is finished too
    if result.status not in (("completed", "time_limit") if config.max_minutes else ("completed",)):
        from ..errors import ESGSError

        raise ESGSError(f"run {task.name} ended with status {result.status}", path=task.out,
                        hint="run the experiment again to resume it")
    metrics = result.metrics or {}
    summary: dict[str, Any] = {
        "name": task.name, "variant": task.variant, "seed": task.seed, "scene": task.scene_name or str(task.scene),
        "status": result.status, "steps": result.step, "iterations": config.iterations,
        "max_minutes": config.max_minutes or None, "n_gaussians": result.n_gaussians,
        "psnr": metrics.get("psnr"), "ssim": metrics.get("ssim"), "lpips": metrics.get("lpips"),
        # training seconds only (the end-of-run evaluation and file writes left out, as the
        # bench's tables say); runs resumed from before train_s existed give their elapsed time
        "train_s": result.train_s if result.train_s is not None else result.elapsed_s,
        "wall_s": wall_s, "peak_memory_mib": peak_memory_mib(),
        "distance_mean": None, "distance_std": None,
    }
    if task.mesh is not None and Path(task.mesh).is_file():
        summary.update(geometry_figures(result.point_cloud, Path(task.mesh)))
    if task.measure_render:
        summary["render_s_per_frame"] = render_seconds_per_frame(Path(task.out))
    atomic_write_json(task.summary_path, summary)
    return summary
