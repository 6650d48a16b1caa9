"""The pinned sets are pinned, and the build requirement can read the project's metadata."""
from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PIN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*==[0-9][0-9A-Za-z.+-]*$")


def _requirement_lines(path: Path) -> list[str]:
    lines = []
    for raw in path.read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if line:
            lines.append(line)
    return lines


def test_requirement_files_pin_every_package_exactly():
    for name in ("requirements.txt", "requirements-trainer.txt"):
        lines = _requirement_lines(ROOT / name)
        assert lines, name
        loose = [line for line in lines if not PIN.match(line)]
        assert not loose, f"{name}: not pinned with ==: {loose}"


def test_the_build_backend_reads_the_spdx_licence_string():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert isinstance(project["project"]["license"], str)  # an SPDX expression: setuptools >= 77
    requires = project["build-system"]["requires"]
    floor = next(r for r in requires if r.startswith("setuptools"))
    assert re.fullmatch(r"setuptools>=(\d+)", floor) and int(floor.split(">=")[1]) >= 77
    pinned = next(line for line in _requirement_lines(ROOT / "requirements.txt") if line.startswith("setuptools=="))
    assert int(pinned.split("==")[1].split(".")[0]) >= 77  # make setup's editable install builds without isolation
