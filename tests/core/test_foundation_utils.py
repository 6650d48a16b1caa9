"""The shared plumbing: settings dataclasses, atomic writes, progress events, the CLI."""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from esgs.core import config as cfg
from esgs.core.errors import ConfigError, DatasetError, ESGSError
from esgs.core.io_utils import atomic_directory, atomic_path, atomic_write_json
from esgs.core.progress import JsonLinesProgress, ProgressEvent, combine


@dataclass
class _Settings:
    iterations: int = field(default=100, metadata={"help": "steps"})
    fov_deg: float = 45.0
    name: str = "x"
    masks: bool = True
    resolution: tuple[int, int] = (480, 270)
    out: Path | None = None

    def validate(self) -> None:
        if self.iterations <= 0:
            raise ConfigError(f"iterations must be positive, got {self.iterations}")


def test_cli_flags_derive_from_dataclass():
    parser = argparse.ArgumentParser()
    cfg.add_dataclass_arguments(parser, _Settings)
    args = parser.parse_args(["--iterations", "7", "--no-masks", "--resolution", "64", "32", "--out", "r"])
    settings = cfg.dataclass_from_args(_Settings, args)
    assert settings == _Settings(iterations=7, masks=False, resolution=(64, 32), out=Path("r"))
    untouched = cfg.dataclass_from_args(_Settings, parser.parse_args([]), base=_Settings(fov_deg=60.0))
    assert untouched.fov_deg == 60.0 and untouched.iterations == 100


def test_config_round_trip_and_errors(tmp_path):
    settings = _Settings(iterations=3, resolution=(8, 4), out=Path("a/b"))
    cfg.save_config(settings, tmp_path / "c.json")
    assert cfg.load_config(_Settings, tmp_path / "c.json") == settings
    (tmp_path / "bad.json").write_text('{"iterations": 5, "colour": 1}')
    with pytest.raises(ConfigError, match="unknown setting.*colour") as info:
        cfg.load_config(_Settings, tmp_path / "bad.json")
    assert "bad.json" in str(info.value)
    (tmp_path / "neg.json").write_text('{"iterations": -1}')
    with pytest.raises(ConfigError, match="iterations must be positive"):
        cfg.load_config(_Settings, tmp_path / "neg.json")
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(ConfigError, match="not valid JSON"):
        cfg.load_config(_Settings, tmp_path / "broken.json")


def test_error_messages_name_file_and_hint():
    err = DatasetError("cameras.bin is truncated", path="/x/sparse/0", hint="re-export the model")
    assert isinstance(err, ESGSError)
    assert str(err) == "/x/sparse/0: cameras.bin is truncated (re-export the model)"


def test_atomic_path_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "a.json"
    atomic_write_json(target, {"v": 1})
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash while writing")
    assert json.loads(target.read_text()) == {"v": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_atomic_directory_leaves_nothing_on_failure(tmp_path):
    out = tmp_path / "scene"
    with pytest.raises(ValueError):
        with atomic_directory(out) as tmp:
            (tmp / "images").mkdir()
            raise ValueError("render failed")
    assert list(tmp_path.iterdir()) == []
    with atomic_directory(out) as tmp:
        (tmp / "ok.txt").write_text("1")
    assert (out / "ok.txt").read_text() == "1"
    with pytest.raises(ConfigError, match="already exists"):
        with atomic_directory(out):
            pass
    with atomic_directory(out, overwrite=True) as tmp:
        (tmp / "new.txt").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == ["new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_json_lines_progress_round_trip(tmp_path):
    seen = []
    writer = JsonLinesProgress(tmp_path / "events.jsonl")
    forward = combine(writer, seen.append, None)
    forward(ProgressEvent(step=1, total=10, stage="train", metrics={"loss": 0.5}))
    forward(ProgressEvent(step=10, total=10, stage="train", kind="done"))
    writer.close()
    lines = (tmp_path / "events.jsonl").read_text().splitlines()
    events = [ProgressEvent.from_json(line) for line in lines]
    assert events == seen
    assert events[0].metrics == {"loss": 0.5} and events[1].kind == "done"


def test_cli_help_lists_subcommands_and_errors_without_traceback():
    result = subprocess.run([sys.executable, "-m", "esgs.core", "--help"], capture_output=True, text=True)
    assert result.returncode == 0
    assert "info" in result.stdout and "build-extension" in result.stdout
    result = subprocess.run([sys.executable, "-m", "esgs.core", "build-extension", "--platform", "nope",
                             "--out", "/tmp/esgs-never"], capture_output=True, text=True)
    assert result.returncode == 2
    assert "unknown platform" in result.stderr and "Traceback" not in result.stderr


def test_console_script_is_installed():
    bindir = Path(sys.executable).parent
    result = subprocess.run([str(bindir / "esgs"), "info", "--json"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    info = json.loads(result.stdout)
    assert info["numpy"].startswith("1.") and info["esgs"]


def test_atomic_files_get_ordinary_permissions(tmp_path):
    import os
    import stat

    target = tmp_path / "m.json"
    atomic_write_json(target, {})
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~mask


def test_cli_help_does_not_load_torch():
    code = "import sys, esgs.core.cli as cli; cli.build_parser(); print('torch' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "False", "esgs --help must stay instant: keep torch imports inside run()"
