"""The one exception family of the project.

Every message says which file (when there is one), what is wrong and what to do.
Operators turn these into ``self.report({'ERROR'}, str(err))``; the CLI prints
them without a traceback.
"""
from __future__ import annotations

from pathlib import Path


class ESGSError(Exception):
    """Base class of every error the project raises on purpose."""

    def __init__(self, message: str, *, path: str | Path | None = None, hint: str | None = None):
        # kept apart from the formatted text so a child process can send the parts to its parent
        self.message = message
        self.path = Path(path) if path is not None else None
        self.hint = hint
        text = f"{self.path}: {message}" if self.path is not None else message
        if hint:
            text = f"{text} ({hint})"
        super().__init__(text)


class DatasetError(ESGSError):
    """A scene folder, COLMAP model, image, prior map or mesh is missing or malformed."""


class ConfigError(ESGSError):
    """A setting is out of range, unknown, or inconsistent with another."""


class CheckpointError(ESGSError):
    """A checkpoint or run folder cannot be read, written or resumed."""


class FormatError(DatasetError):
    """A file is not in the format it claims (PLY, EXR, COLMAP binary...)."""
