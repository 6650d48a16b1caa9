"""Typed settings: dataclasses are the single source of every option.

The CLI flags (:func:`add_dataclass_arguments`), the saved run config
(:func:`config_to_dict` / :func:`config_from_dict`) and the Blender properties are all
derived from the dataclass fields, so an option exists in one place. Each field's
help text is ``field(metadata={"help": "..."})``; units go in the name (``fov_deg``).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from .errors import ConfigError

T = TypeVar("T")


def _resolved_fields(cls: type) -> list[tuple[dataclasses.Field, Any]]:
    hints = typing.get_type_hints(cls)
    return [(f, hints[f.name]) for f in dataclasses.fields(cls) if f.init]


def _base_type(annotation: Any) -> Any:
    origin = typing.get_origin(annotation)
    if origin is typing.Union or origin is types.UnionType:
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return _base_type(args[0]) if len(args) == 1 else annotation
    return annotation


def add_dataclass_arguments(parser: argparse.ArgumentParser, cls: type, *, prefix: str = "",
                            skip: tuple[str, ...] = ()) -> None:
    """Add one ``--flag`` per field of dataclass ``cls`` (underscores become dashes).

    bool fields get ``--name/--no-name``; tuple/list fields take several values. Defaults
    are left as ``None`` in argparse so :func:`dataclass_from_args` can tell what was set.
    """
    for fld, annotation in _resolved_fields(cls):
        if fld.name in skip:
            continue
        flag = "--" + (prefix + fld.name).replace("_", "-")
        default = _field_default(fld)
        help_text = fld.metadata.get("help", "")
        if default is not dataclasses.MISSING:
            help_text = f"{help_text} (default: {default})".strip()
        base = _base_type(annotation)
        origin = typing.get_origin(base)
        dest = prefix + fld.name
        if base is bool:
            parser.add_argument(flag, dest=dest, action=argparse.BooleanOptionalAction, default=None, help=help_text)
        elif origin in (tuple, list):
            item = typing.get_args(base)[0] if typing.get_args(base) else str
            parser.add_argument(flag, dest=dest, nargs="+", type=item, default=None, help=help_text)
        elif base in (int, float, str):
            parser.add_argument(flag, dest=dest, type=base, default=None, help=help_text,
                                choices=fld.metadata.get("choices"))
        elif base is Path:
            parser.add_argument(flag, dest=dest, type=Path, default=None, help=help_text)
        # nested dataclasses and other types are config-file only


def _field_default(fld: dataclasses.Field) -> Any:
    if fld.default is not dataclasses.MISSING:
        return fld.default
    if fld.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return fld.default_factory()  # type: ignore[misc]
    return dataclasses.MISSING


def dataclass_from_args(cls: type[T], args: argparse.Namespace, *, prefix: str = "", base: T | None = None) -> T:
    """Build ``cls`` from parsed arguments; unset flags keep ``base``'s (or the default) values."""
    values = config_to_dict(base) if base is not None else {}
    for fld, annotation in _resolved_fields(cls):
        value = getattr(args, prefix + fld.name, None)
        if value is not None:
            if typing.get_origin(_base_type(annotation)) is tuple:
                value = tuple(value)
            values[fld.name] = value
    return config_from_dict(cls, values)


def config_to_dict(config: Any) -> dict[str, Any]:
    """A JSON-ready dict of a (possibly nested) settings dataclass."""
    def convert(value: Any) -> Any:
        if dataclasses.is_dataclass(value):
            return {f.name: convert(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, (list, tuple)):
            return [convert(v) for v in value]
        if isinstance(value, Path):
            return str(value)
        return value

    return convert(config)


def config_from_dict(cls: type[T], data: dict[str, Any], *, source: str | Path | None = None) -> T:
    """Build ``cls`` from a dict, rejecting unknown keys with a clear error."""
    known = {f.name: (f, a) for f, a in _resolved_fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ConfigError(f"unknown setting(s) {', '.join(unknown)} for {cls.__name__}",
                          path=source, hint=f"known: {', '.join(sorted(known))}")
    kwargs = {}
    for name, value in data.items():
        _, annotation = known[name]
        base = _base_type(annotation)
        if dataclasses.is_dataclass(base) and isinstance(value, dict):
            value = config_from_dict(base, value, source=source)
        elif typing.get_origin(base) is tuple and isinstance(value, list):
            value = tuple(value)
        elif base is Path and isinstance(value, str):
            value = Path(value)
        kwargs[name] = value
    try:
        config = cls(**kwargs)
    except (TypeError, ValueError) as err:
        raise ConfigError(str(err), path=source) from err
    validate = getattr(config, "validate", None)
    if callable(validate):
        validate()
    return config


def save_config(config: Any, path: str | Path) -> None:
    """Write a settings dataclass as JSON, atomically."""
    from .io_utils import atomic_write_json

    atomic_write_json(path, config_to_dict(config))


def read_json_object(path: str | Path, *, what: str = "config file") -> dict[str, Any]:
    """The JSON object in ``path``; ConfigError naming the file when it is missing, unreadable,
    not JSON or not an object (``what`` names the file in the message)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise ConfigError(f"{what} not found", path=path) from err
    except OSError as err:
        raise ConfigError(f"cannot read the {what}: {err}", path=path) from err
    except json.JSONDecodeError as err:
        raise ConfigError(f"not valid JSON: {err}", path=path) from err
    if not isinstance(data, dict):
        raise ConfigError("expected a JSON object", path=path)
    return data


def load_config(cls: type[T], path: str | Path) -> T:
    """Read a settings dataclass written by :func:`save_config`."""
    return config_from_dict(cls, read_json_object(path), source=Path(path))
