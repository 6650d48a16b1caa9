"""Render a trained run from its scene's cameras (the ``esgs render`` command)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import torch

from ..errors import DatasetError
from .method import RenderOptions


def render_run(run_dir: str | Path, *, cameras: Optional[Sequence[str]] = None, output: Optional[Path] = None,
               depth: bool = False, backend: Optional[str] = None, render: Optional[RenderOptions] = None) -> list[Path]:
    """Render cameras (image names or stems; None = all) of a run; returns the written files.

    ``render``: the run's method's render options (default: plain 3DGS rendering;
    :func:`esgs.core.methods.render_run` passes the right ones for any method).

    Colour goes to ``<output>/<stem>.png`` and, with ``depth``, the expected camera-z depth
    to ``<stem>_depth.exr`` (0 where nothing was hit).
    """
    from ..formats.imageio import write_depth_exr, write_png
    from .evaluate import _to_uint8, load_run, load_run_sky
    from .rendering import render_view
    from ..formats.run_dir import RunDir

    run = RunDir(Path(run_dir))
    render = render or RenderOptions()
    config, data, model, name, device = load_run(run.root, backend=backend)
    views = sorted(data.train + data.test, key=lambda view: view.index)
    if cameras is not None:
        by_name = {view.name: view for view in views}
        by_name.update({view.stem: view for view in views})
        missing = [camera for camera in cameras if camera not in by_name]
        if missing:
            raise DatasetError(f"no camera named {', '.join(missing)} in the scene", path=config.scene,
                               hint=f"cameras: {', '.join(v.name for v in views[:10])}{'...' if len(views) > 10 else ''}")
        views = [by_name[camera] for camera in cameras]
    output = Path(output) if output is not None else run.renders / "cameras"
    background = torch.tensor(config.background, dtype=torch.float32, device=device)
    sky = load_run_sky(run.root, device)
    written = []
    with torch.no_grad():
        params = model.render_params(model.max_sh_degree)
        for view in views:
            result = render_view(params, view.viewmat.to(device), view.K.to(device), view.width, view.height,
                                 background=background, render_depth=depth, backend=name,
                                 num_threads=config.threads or None,
                                 antialiased=render.antialiased, eps2d=render.eps2d, sky=sky)
            written.append(write_png(output / f"{view.stem}.png", _to_uint8(result.image)))
            if depth:
                path = output / f"{view.stem}_depth.exr"
                write_depth_exr(path, result.depth[:, :, 0].cpu().numpy())
                written.append(path)
    return written
