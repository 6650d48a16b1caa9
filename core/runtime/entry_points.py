"""The one registry of child-process entry points.

``core`` never imports ``bpy`` or the add-on, yet some jobs need Blender (scene rendering,
label rendering, the results .blend). Those children are named here, by module string,
and nowhere else: every parent starts a job by its name (``"scene"``), and the child
(:mod:`.child`) imports the module it names. A test checks that every module exists
(``importlib.util.find_spec``, without importing bpy) and that no other core module spells
an add-on module or ``-m esgs.core`` by hand.

A job's function takes ``(data, context)``: ``data`` is the JSON object of the job's
config file (written from its settings dataclass with :func:`esgs.core.config.config_to_dict`),
``context`` a :class:`esgs.core.runtime.child.ChildContext` (progress callback, stop file).
It returns a JSON-ready value (the parent's result) or None, and raises our errors
(:mod:`esgs.core.errors`) for handled failures.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Callable

from ..errors import ConfigError

#: The top-level package name the child process imports. An installed extension lives in a
#: folder named after its id, ``esgs``; the parent puts that folder's parent on the child's
#: ``PYTHONPATH`` (see :func:`esgs.core.runtime.process.child_environment`), so the child
#: imports the very same engine under this name even when Blender loaded it as ``bl_ext.*``.
PACKAGE = "esgs"

#: The module a child process runs: ``python -m esgs.core.runtime.child JOB CONFIG ...``.
CHILD_MODULE = f"{PACKAGE}.core.runtime.child"


@dataclass(frozen=True)
class EntryPoint:
    """Where a job's child-side function lives.

    ``module`` is relative to the package root (``"esgs_addon.make_scene"``);
    ``watches_stop_file`` says the function polls ``context.stop_file`` itself (the
    trainer: it checkpoints first); otherwise the child turns the stop file into a
    KeyboardInterrupt so the job's clean-up (``finally``, staging folders) runs.
    ``needs_bpy`` marks the Blender children (documentation and the no-bpy test).
    """

    module: str
    function: str
    watches_stop_file: bool = False
    needs_bpy: bool = False

    @property
    def absolute_module(self) -> str:
        """The module's import name in a child process (``esgs.esgs_addon.make_scene``)."""
        return f"{PACKAGE}.{self.module}"


#: Every job a parent may start in a child process, by name.
ENTRY_POINTS: dict[str, EntryPoint] = {
    "train": EntryPoint("core.methods.train_job", "child_job", watches_stop_file=True),
    "priors": EntryPoint("core.priors.job", "child_job"),
    "labels": EntryPoint("core.labels.pipeline", "child_job"),
    "scene": EntryPoint("esgs_addon.make_scene", "child_job", needs_bpy=True),
    "render_labels": EntryPoint("esgs_addon.render_labels", "child_job", needs_bpy=True),
    "results_scene": EntryPoint("esgs_addon.results_scene", "child_job", needs_bpy=True),
}


def entry_point(job: str) -> EntryPoint:
    """The entry point of ``job``.

    Raises:
        ConfigError: no job of that name is registered.
    """
    try:
        return ENTRY_POINTS[job]
    except KeyError:
        raise ConfigError(f"unknown child job {job!r}", hint=f"known: {', '.join(sorted(ENTRY_POINTS))}") from None


def load_job_function(job: str, package: str = PACKAGE) -> Callable[[dict[str, Any], Any], Any]:
    """Import and return the child-side function of ``job`` (child side only: a Blender
    job's module needs the bpy module). ``package`` is the child's top-level package."""
    entry = entry_point(job)
    module = importlib.import_module(f"{package}.{entry.module}")
    return getattr(module, entry.function)
