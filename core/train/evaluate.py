"""Held-out evaluation: PSNR, SSIM and LPIPS per view and their means, renders beside ground truth.

``metrics.json`` (see docs/training.md)::

    {"split": "test", "views_count": 3, "psnr": 24.1, "ssim": 0.81, "lpips": 0.21 | null,
     "lpips_unavailable": null | "why", "views": [{"name": ..., "psnr": ..., "ssim": ..., "lpips": ...}],
     "n_gaussians": ..., "step": ...}

Metrics are computed on the whole image (masks are a training aid only), on renders
clamped to [0, 1], with :mod:`esgs.core.metrics`. When a scene has no test split
(``test_every = 0``) the training views are evaluated and ``split`` says "train".
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import torch

from ..errors import CheckpointError
from ..progress import ProgressCallback, ProgressEvent
from .gaussians import GaussianModel, RenderParams
from .method import RenderOptions


def _to_uint8(image: torch.Tensor) -> np.ndarray:
    return (image.detach().clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def _lpips_model(use_lpips: bool) -> tuple[Any, Optional[str]]:
    if not use_lpips:
        return None, "disabled (lpips = false)"
    try:
        from ..metrics.lpips import LPIPS

        # never download during a run: evaluation uses cached weights or reports why not
        return LPIPS(download=False), None
    except ImportError as err:
        return None, f"LPIPS module not available: {err}"
    except Exception as err:  # noqa: BLE001 - LPIPSUnavailableError and damaged caches alike
        return None, str(err)


def evaluate_model(model: GaussianModel, data: Any, *, backend: str, background: torch.Tensor, sh_degree: int,
                   renders_dir: Optional[Path] = None, use_lpips: bool = True, num_threads: Optional[int] = None,
                   progress: Optional[ProgressCallback] = None, views: Optional[list] = None,
                   antialiased: bool = False, eps2d: float = 0.3, sky: Any = None,
                   view_params: Optional[Callable[[Any, RenderParams], RenderParams]] = None) -> dict:
    """Render every held-out view of ``data`` (or ``views``) and measure it against its image.

    ``antialiased``/``eps2d``: render with the rasterizer's 2D filter (runs trained with Mip-Splatting);
    ``sky``: the run's :class:`~.sky.SkyModel`, composited behind the Gaussians (None: ``background``);
    ``view_params(view, params) -> params``: the parameters each view is rendered with (the
    trainer's hooks, for methods whose model depends on the view: Scaffold-GS); None: ``model``'s
    own for every view.
    """
    from ..formats.imageio import write_png
    from ..metrics.image import psnr, ssim
    from .rendering import render_view

    split = "test"
    if views is None:
        views = data.test
        if not views:
            views, split = data.train, "train"
    lpips_model, lpips_reason = _lpips_model(use_lpips)
    device = background.device
    if lpips_model is not None:
        lpips_model = lpips_model.to(device)
    rows = []
    with torch.no_grad():
        params = model.render_params(sh_degree)
        for number, view in enumerate(views):
            shown = params if view_params is None else view_params(view, params)
            output = render_view(shown, view.viewmat.to(device), view.K.to(device), view.width, view.height,
                                 background=background, backend=backend, num_threads=num_threads,
                                 antialiased=antialiased, eps2d=eps2d, sky=sky)
            image = output.image.clamp(0.0, 1.0).permute(2, 0, 1)[None]
            target = view.image_float(device).permute(2, 0, 1)[None]
            row = {"name": view.name, "psnr": float(psnr(image, target)), "ssim": float(ssim(image, target)),
                   "lpips": None}
            if lpips_model is not None:
                try:
                    row["lpips"] = float(lpips_model(image, target)[0])
                except Exception as err:  # noqa: BLE001 - e.g. images smaller than AlexNet's minimum
                    lpips_model, lpips_reason = None, str(err)
            rows.append(row)
            if renders_dir is not None:
                write_png(Path(renders_dir) / f"{view.stem}.png", _to_uint8(output.image))
                write_png(Path(renders_dir) / f"{view.stem}_gt.png", view.image.cpu().numpy())
            if progress is not None:
                progress(ProgressEvent(step=number + 1, total=len(views), stage="eval",
                                       metrics={"psnr": row["psnr"], "ssim": row["ssim"]}))
    if lpips_model is None:
        for row in rows:
            row["lpips"] = None
    metrics = {
        "split": split,
        "views_count": len(rows),
        "psnr": float(np.mean([r["psnr"] for r in rows])) if rows else None,
        "ssim": float(np.mean([r["ssim"] for r in rows])) if rows else None,
        "lpips": float(np.mean([r["lpips"] for r in rows])) if rows and lpips_model is not None else None,
        "lpips_unavailable": None if lpips_model is not None else lpips_reason,
        "n_gaussians": len(model),
        "sh_degree": sh_degree,
        "views": rows,
    }
    return metrics


def load_run_model(run_dir: str | Path) -> GaussianModel:
    """The trained Gaussians of a run: ``point_cloud.ply``, or the newest checkpoint if no PLY yet."""
    from ..formats.ply import read_gaussians_ply
    from .checkpoint import latest_checkpoint, load_checkpoint
    from ..formats.run_dir import RunDir

    run = RunDir(Path(run_dir))
    if run.point_cloud.is_file():
        return GaussianModel.from_ply(read_gaussians_ply(run.point_cloud))
    latest = latest_checkpoint(run.checkpoints)
    if latest is None:
        raise CheckpointError("the run has neither point_cloud.ply nor a checkpoint", path=run.root,
                              hint="train it first (esgs train SCENE --out RUN)")
    return GaussianModel.from_state_dict(load_checkpoint(latest)["gaussians"])


def load_run(run_dir: str | Path, *, backend: Optional[str] = None):
    """(config, scene data, model, backend, device) of a finished or interrupted run.

    ``config.method_config`` is left as saved (a dict); the method's render options come from
    :func:`esgs.core.methods.render_options`."""
    from .config import load_run_config
    from .dataset import load_scene_data
    from .rendering import backend_device, resolve_backend
    from ..formats.run_dir import RunDir

    run = RunDir(Path(run_dir))
    if not run.config.is_file():
        raise CheckpointError("not a run folder (no config.json)", path=run.root, hint="pass the --out folder of esgs train")
    config = load_run_config(run.config)
    data = load_scene_data(config.scene, images_dir=config.images_dir, resolution=config.resolution,
                           width=config.width, test_every=config.test_every, mask_source=config.mask_source)
    name = resolve_backend(backend or config.backend)
    device = backend_device(name)
    model = load_run_model(run.root).to(device)
    return config, data, model, name, device


def load_run_sky(run_dir: str | Path, device: Any = "cpu") -> Any:
    """The run's sky model on ``device``, from where :func:`load_run_model` takes the Gaussians:
    ``RUN/sky.json`` beside ``point_cloud.ply`` (both written at the end of a session), else the
    newest checkpoint's. None for a run with ``sky = none`` or without one."""
    from ..formats.run_dir import RunDir
    from .checkpoint import latest_checkpoint, load_checkpoint
    from .config import load_run_config
    from .sky import SkyModel, load_sky

    run = RunDir(Path(run_dir))
    if run.config.is_file() and load_run_config(run.config).sky == "none":
        return None  # a sky.json left in the folder by another run is not this run's
    if run.point_cloud.is_file():
        sky = load_sky(run.sky)
    else:
        latest = latest_checkpoint(run.checkpoints)
        state = load_checkpoint(latest).get("sky") if latest is not None else None
        sky = SkyModel.from_dict(state, source=latest) if state else None
    return sky.to(device) if sky is not None else None


def evaluate_run(run_dir: str | Path, *, backend: Optional[str] = None, save_renders: bool = True,
                 use_lpips: bool = True, progress: Optional[ProgressCallback] = None,
                 render: Optional[RenderOptions] = None) -> dict:
    """Evaluate a run folder on its held-out views; writes and returns ``metrics.json``'s content.

    ``render``: the run's method's render options (default: plain 3DGS rendering);
    :func:`esgs.core.methods.evaluate_run` passes the right ones for any method."""
    from ..io_utils import atomic_write_json
    from ..formats.run_dir import RunDir

    run = RunDir(Path(run_dir))
    render = render or RenderOptions()
    config, data, model, name, device = load_run(run.root, backend=backend)
    if config.threads:
        torch.set_num_threads(config.threads)
    background = torch.tensor(config.background, dtype=torch.float32, device=device)
    metrics = evaluate_model(model, data, backend=name, background=background, sh_degree=model.max_sh_degree,
                             renders_dir=run.test_renders if save_renders else None, use_lpips=use_lpips,
                             num_threads=config.threads or None, progress=progress,
                             antialiased=render.antialiased, eps2d=render.eps2d, sky=load_run_sky(run.root, device))
    atomic_write_json(run.metrics, metrics)
    return metrics
