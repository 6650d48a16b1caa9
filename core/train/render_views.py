"""Render a trained run from its scene's cameras (the ``esgs render`` command)."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Optional, Sequence

import torch

from ..errors import DatasetError
from .method import RenderOptions

if TYPE_CHECKING:
    from .rendering import RenderOutput


class RunRenderer:
    """A finished run loaded once, rendering its scene's views the way training showed them.

    Its model at full SH degree, its sky, background and backend (``backend`` overrides the
    saved one) and ``render`` (the method's render options; default plain 3DGS rendering:
    :func:`esgs.core.methods.run_renderer` passes the right ones for any method). The one
    place a run's views are rendered for ``esgs render`` and the studies' per-view figures.
    """

    def __init__(self, run_dir: str | Path, *, backend: Optional[str] = None,
                 render: Optional[RenderOptions] = None):
        from .evaluate import load_run, load_run_sky

        self.config, self.data, self.model, self.backend, self.device = load_run(Path(run_dir), backend=backend)
        self.sky = load_run_sky(Path(run_dir), self.device)
        self.render_options = render or RenderOptions()
        self._background = torch.tensor(self.config.background, dtype=torch.float32, device=self.device)
        self._params = None

    def views(self, split: str = "all") -> list:
        """The scene's views: "train", "test" (held out) or "all" (in capture order)."""
        if split == "train":
            return list(self.data.train)
        if split == "test":
            return list(self.data.test)
        if split == "all":
            return sorted(self.data.train + self.data.test, key=lambda view: view.index)
        raise ValueError(f"split must be train, test or all, got {split!r}")

    def render(self, view, *, depth: bool = False, normals: bool = False) -> "RenderOutput":
        """One view, without gradients (colour with the run's sky; expected depth with ``depth``,
        composited camera-frame normals with ``normals``)."""
        from .rendering import render_view

        with torch.no_grad():
            if self._params is None:
                self._params = self.model.render_params(self.model.max_sh_degree)
            return render_view(self._params, view.viewmat.to(self.device), view.K.to(self.device), view.width,
                               view.height, background=self._background, render_depth=depth,
                               render_normals=normals, backend=self.backend,
                               num_threads=self.config.threads or None, antialiased=self.render_options.antialiased,
                               eps2d=self.render_options.eps2d, sky=self.sky)


def render_run(run_dir: str | Path, *, cameras: Optional[Sequence[str]] = None, output: Optional[Path] = None,
               depth: bool = False, backend: Optional[str] = None, render: Optional[RenderOptions] = None) -> list[Path]:
    """Render cameras (image names or stems; None = all) of a run; returns the written files.

    ``render``: the run's method's render options (default: plain 3DGS rendering;
    :func:`esgs.core.methods.render_run` passes the right ones for any method).

    Colour goes to ``<output>/<stem>.png`` and, with ``depth``, the expected camera-z depth
    to ``<stem>_depth.exr`` (0 where nothing was hit).
    """
    from ..formats.imageio import write_depth_exr, write_png
    from .evaluate import _to_uint8
    from ..formats.run_dir import RunDir

    run = RunDir(Path(run_dir))
    renderer = RunRenderer(run.root, backend=backend, render=render)
    views = renderer.views("all")
    if cameras is not None:
        by_name = {view.name: view for view in views}
        by_name.update({view.stem: view for view in views})
        missing = [camera for camera in cameras if camera not in by_name]
        if missing:
            raise DatasetError(f"no camera named {', '.join(missing)} in the scene", path=renderer.config.scene,
                               hint=f"cameras: {', '.join(v.name for v in views[:10])}{'...' if len(views) > 10 else ''}")
        views = [by_name[camera] for camera in cameras]
    output = Path(output) if output is not None else run.renders / "cameras"
    written = []
    for view in views:
        result = renderer.render(view, depth=depth)
        written.append(write_png(output / f"{view.stem}.png", _to_uint8(result.image)))
        if depth:
            path = output / f"{view.stem}_depth.exr"
            write_depth_exr(path, result.depth[:, :, 0].cpu().numpy())
            written.append(path)
    return written
