"""Set up the trainer: a Python 3.11 virtual environment with the engine's runtime requirements.

A user who installed only the extension zip has no Python with torch. *Set Up Trainer*
(Preferences) builds one in the extension's user directory:

1. ``python -m venv`` with Blender's own interpreter (3.11, as the engine needs);
2. torch alone first, from the PyTorch index of the chosen build (``cpu``, or ``cuda`` when
   an NVIDIA GPU is found), so no looser range pulls another build later;
3. the rest of ``requirements-trainer.txt`` (shipped in the extension), with the extension's
   ``wheels/`` folder offered as a local source;
4. the engine itself from the extension's files: a ``.pth`` file naming the folder that holds
   the extension's ``esgs`` folder, so ``python -m esgs.core...`` in the child imports the very
   files Blender loaded as ``bl_ext.<repository>.esgs`` (a copy when the folder has another name);
5. a check: import the engine and the requirements and render a few Gaussians with
   :func:`esgs.core.render.rasterization`.

Everything is built in a hidden folder beside the target and renamed into place only once
verified; a failure or a cancel removes it, and an earlier environment stays as it was.
A virtual environment survives being renamed as long as it is used through its
``python`` (``python -m pip``), never through the scripts' shebang lines, which is all we do.

No bpy here: the operator (``operators/trainer_setup.py``) and headless scripts call
:func:`run_setup` or :class:`SetupJob`, and the tests run it with plain Python.
"""
from __future__ import annotations

import collections
import dataclasses
import json
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Iterable, Optional, Sequence

from ..core.errors import ESGSError

#: the extension's (and the checkout's) root folder, whose name is the package name ``esgs``
#: when Blender installed it as an extension
PACKAGE_ROOT = Path(__file__).resolve().parents[1]
REQUIREMENTS_NAME = "requirements-trainer.txt"
#: the name of the environment's folder inside the extension's user directory
ENVIRONMENT_NAME = "trainer"
#: the import name the child process uses (``python -m esgs.core.runtime.child``)
ENGINE_PACKAGE = "esgs"
ENGINE_PTH_NAME = "esgs_engine.pth"

VARIANTS = ("cpu", "cuda")
#: PyTorch's own indexes; they also serve torch's dependencies
TORCH_INDEX = {
    "cpu": "https://download.pytorch.org/whl/cpu",
    "cuda": "https://download.pytorch.org/whl/cu128",
}
#: requirement name -> the module the check imports
REQUIREMENT_MODULES = {
    "torch": "torch", "numpy": "numpy", "numba": "numba", "scipy": "scipy",
    "opencv-contrib-python-headless": "cv2", "openexr": "OpenEXR", "trimesh": "trimesh",
    "pycolmap": "pycolmap", "tqdm": "tqdm",
}

#: pip output that means the package index (or a proxy in front of it) was not reached
_UNREACHABLE_MARKERS = (
    "NewConnectionError", "Failed to establish a new connection", "Temporary failure in name resolution",
    "Name or service not known", "nodename nor servname", "getaddrinfo failed", "ConnectTimeoutError",
    "Read timed out", "ProxyError", "Network is unreachable", "No route to host", "SSLError",
    "Could not fetch URL",
)
_NOT_FOUND_MARKERS = ("No matching distribution found", "Could not find a version that satisfies")

OFFLINE_HINT = ("if this machine cannot reach the package index, either point Preferences > Trainer Python at an "
                "existing Python 3.11 that has the packages of requirements-trainer.txt (the python of its "
                "virtual environment: bin/python, or Scripts\\python.exe on Windows), or download the wheels "
                "elsewhere (pip download -r requirements-trainer.txt -d WHEELS, with --index-url "
                f"{TORCH_INDEX['cpu']} for torch) and choose that folder as Preferences > Wheel Folder")


class TrainerSetupError(ESGSError):
    """Setting up the trainer environment failed; nothing was left behind."""


class SetupCancelled(TrainerSetupError):
    """The set-up was cancelled; nothing was left behind."""


@dataclasses.dataclass(frozen=True)
class SetupCommand:
    """One step of the set-up: a label for the user and the command it runs.

    ``kind`` is one of ``venv``, ``torch``, ``requirements``, ``engine``, ``verify``; the
    verify step prints its findings as JSON on its last line.
    """

    kind: str
    label: str
    argv: tuple[str, ...]


# --------------------------------------------------------------------------- finding things


def venv_python(env_dir: str | os.PathLike, *, windows: Optional[bool] = None) -> Path:
    """The interpreter of a virtual environment: ``bin/python`` (Linux, macOS) or
    ``Scripts/python.exe`` (Windows)."""
    windows = os.name == "nt" if windows is None else windows
    return Path(env_dir) / ("Scripts/python.exe" if windows else "bin/python")


def environment_python(env_dir: str | os.PathLike) -> Optional[Path]:
    """The set-up environment's interpreter when the environment exists, else None."""
    python = venv_python(env_dir)
    return python if python.is_file() else None


def detect_variant(which: Optional[Callable[[str], Optional[str]]] = None,
                   platform: Optional[str] = None) -> tuple[str, str]:
    """``(variant, reason)``: ``cuda`` when ``nvidia-smi`` is on the PATH (not on macOS, which
    has no CUDA), else ``cpu``."""
    which = which or shutil.which
    if (platform or sys.platform) == "darwin":
        return "cpu", "macOS: PyTorch uses the CPU (and Apple's GPU through MPS) with the standard build"
    smi = which("nvidia-smi")
    if smi:
        return "cuda", f"an NVIDIA GPU driver was found ({smi})"
    return "cpu", "no NVIDIA GPU found (nvidia-smi is not on the PATH)"


def requirements_path(engine_dir: str | os.PathLike = PACKAGE_ROOT) -> Path:
    return Path(engine_dir) / REQUIREMENTS_NAME


def read_requirements(path: str | os.PathLike) -> list[str]:
    """The requirement lines of a requirements file (comments and blank lines dropped)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as error:
        raise TrainerSetupError("the trainer's requirements file cannot be read", path=path,
                                hint="reinstall the extension; the file ships inside it") from error
    lines = [line.split("#", 1)[0].strip() for line in text.splitlines()]
    return [line for line in lines if line]


def requirement_name(line: str) -> str:
    """``"torch==2.13.0"`` -> ``"torch"`` (lower case, as pip compares names)."""
    for separator in ("==", ">=", "<=", "~=", "!=", ">", "<", "[", ";", " "):
        line = line.split(separator, 1)[0]
    return line.strip().lower().replace("_", "-")


# --------------------------------------------------------------------------- the plan


def _pip(python: str, *args: str) -> tuple[str, ...]:
    # 2 retries, not pip's 5 with back-off: an unreachable index then fails in about a minute, not many
    return (python, "-m", "pip", "install", "--disable-pip-version-check", "--no-input", "--progress-bar", "off",
            "--retries", "2", *args)


def _source_args(find_links: Sequence[Path], index_url: Optional[str], default_index: Optional[str]) -> list[str]:
    """pip's source options: a wheel folder alone means offline (``--no-index``); an index URL
    given by the user wins over ours."""
    args: list[str] = []
    for folder in find_links:
        args += ["--find-links", str(folder)]
    if index_url:
        args += ["--index-url", index_url]
    elif find_links:
        args.append("--no-index")
    elif default_index:
        args += ["--index-url", default_index]
    return args


def plan_setup(target_dir: str | os.PathLike, *, python: str | os.PathLike, variant: str,
               find_links: str | os.PathLike | Iterable[str | os.PathLike] | None = None,
               index_url: Optional[str] = None, requirements: str | os.PathLike | None = None,
               engine_dir: str | os.PathLike = PACKAGE_ROOT,
               system_site_packages: bool = False) -> list[SetupCommand]:
    """The commands that build the trainer environment in ``target_dir`` (which must not exist).

    Args:
        python: the interpreter that creates the environment (Blender's own Python 3.11).
        variant: ``"cpu"`` or ``"cuda"``: which torch build (its PyTorch index).
        find_links: a folder (or folders) of wheels. Without ``index_url`` the install is
            offline (``--no-index``): everything must be in the folder(s).
        index_url: a package index for every pip step instead of PyPI / PyTorch's index.
        requirements: the requirements file (default: ``requirements-trainer.txt`` of ``engine_dir``).
            Its ``torch`` line, when there is one, is installed first, alone.
        engine_dir: the extension's (the engine's) root folder.
        system_site_packages: let the environment see the creating Python's packages (tests).
    """
    if variant not in VARIANTS:
        raise TrainerSetupError(f"unknown torch build {variant!r}", hint=f"choose one of {', '.join(VARIANTS)}")
    target = Path(target_dir)
    engine = Path(engine_dir).absolute()
    requirements = Path(requirements) if requirements is not None else requirements_path(engine)
    if find_links is None:
        links: list[Path] = []
    elif isinstance(find_links, (str, os.PathLike)):
        links = [Path(find_links)]
    else:
        links = [Path(folder) for folder in find_links]
    for folder in links:
        if not folder.is_dir():
            raise TrainerSetupError("the wheel folder does not exist", path=folder,
                                    hint="choose a folder of .whl files, or clear the setting to use the internet")
    lines = read_requirements(requirements)
    torch_lines = [line for line in lines if requirement_name(line) == "torch"]
    env_python = str(venv_python(target))
    commands = [SetupCommand("venv", f"Create the environment with {python}",
                             (str(python), "-m", "venv", *(["--system-site-packages"] if system_site_packages else []),
                              str(target)))]
    if torch_lines:
        commands.append(SetupCommand("torch", f"Install {torch_lines[0]} ({variant.upper()} build)",
                                     _pip(env_python, *torch_lines, *_source_args(links, index_url,
                                                                                  TORCH_INDEX[variant]))))
    # the wheels Blender installed for the add-on side are the same pinned versions: a free local source
    bundled = engine / "wheels"
    local = links + ([bundled] if bundled.is_dir() and bundled not in links else [])
    commands.append(SetupCommand(
        "requirements", f"Install the requirements ({requirements.name})",
        _pip(env_python, "-r", str(requirements.absolute()),
             *(_source_args(local, index_url, None) if links or index_url else
               [arg for folder in local for arg in ("--find-links", str(folder))]))))
    commands.append(SetupCommand("engine", f"Install the engine from {engine}",
                                 (env_python, "-c", _ENGINE_SCRIPT, str(engine))))
    commands.append(SetupCommand("verify", "Check: import the engine and render a few Gaussians",
                                 (env_python, "-c", VERIFY_SCRIPT, "render",
                                  *sorted({REQUIREMENT_MODULES.get(requirement_name(line), "")
                                           for line in lines} - {""}))))
    return commands


#: Run by the new environment's python with the engine folder as argument: make ``import esgs``
#: find the extension's files. The extension folder is named ``esgs`` (its id), so a .pth file
#: naming its parent does it and follows updates of the extension; a folder with another name
#: (a development checkout) is copied as ``esgs`` instead.
_ENGINE_SCRIPT = r"""
import os, shutil, sys, sysconfig
from pathlib import Path
engine = Path(os.path.abspath(sys.argv[1]))
site = Path(sysconfig.get_paths()["purelib"])
if not (engine / "__init__.py").is_file() or not (engine / "core").is_dir():
    sys.exit(f"{engine} does not hold the esgs engine (no __init__.py and core/)")
if engine.name == "esgs":
    (site / "esgs_engine.pth").write_text(str(engine.parent) + "\n", encoding="utf-8")
    print(f"esgs: {site / 'esgs_engine.pth'} -> {engine.parent}")
else:
    skip = shutil.ignore_patterns(".git", ".venv", ".cache", "__pycache__", "tests", "benchmarks", "wheels",
                                  "dist", "build", "*.egg-info", ".pytest_cache", ".hypothesis")
    shutil.copytree(engine, site / "esgs", ignore=skip)
    print(f"esgs: copied {engine} to {site / 'esgs'}")
"""

#: Run by a trainer python: ``VERIFY_SCRIPT render|check MODULE...``. Imports the engine and the
#: modules, optionally renders 4 Gaussians into a 24x16 image on the CPU backend, and prints one
#: JSON line with what it found (exit status 1 and ``"error"`` when something is missing).
VERIFY_SCRIPT = r"""
import importlib, json, os, platform, sys, time
found = {"python": sys.executable, "prefix": sys.prefix, "version": platform.python_version(), "modules": {}}
def done(code):
    print(json.dumps(found)); sys.exit(code)
try:
    for name in ["torch", "numpy"] + sys.argv[2:]:
        module = importlib.import_module(name)
        found["modules"][name] = str(getattr(module, "__version__", "") or "")
    import torch
    found["torch"], found["numpy"] = torch.__version__, found["modules"]["numpy"]
    found["cuda"] = bool(torch.cuda.is_available())
    found["cuda_version"] = torch.version.cuda
    found["device"] = torch.cuda.get_device_name(0) if found["cuda"] else platform.processor() or platform.machine()
    mps = getattr(torch.backends, "mps", None)
    found["mps"] = bool(mps is not None and mps.is_available())
    found["backend"] = "cuda" if found["cuda"] else "cpu"
    import esgs
    found["engine"] = os.path.dirname(os.path.abspath(esgs.__file__))
    found["engine_version"] = getattr(esgs, "__version__", "")
    if sys.argv[1] == "render":
        from esgs.core.render import rasterization
        start = time.perf_counter()
        means = torch.tensor([[0.0, 0.0, 3.0], [0.3, 0.1, 3.2], [-0.3, -0.1, 2.8], [0.0, 0.2, 3.5]])
        quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(4, 1)
        scales = torch.full((4, 3), 0.2)
        opacities = torch.full((4,), 0.9)
        colors = torch.tensor([[1.0, 0.2, 0.1], [0.1, 1.0, 0.2], [0.2, 0.1, 1.0], [0.5, 0.5, 0.5]])
        viewmats = torch.eye(4)[None]
        Ks = torch.tensor([[[20.0, 0.0, 12.0], [0.0, 20.0, 8.0], [0.0, 0.0, 1.0]]])
        render, alpha, _ = rasterization(means, quats, scales, opacities, colors, viewmats, Ks, 24, 16)
        if tuple(render.shape) != (1, 16, 24, 3) or not bool(torch.isfinite(render).all()) \
                or float(alpha.max()) < 0.5:
            raise RuntimeError(f"the test render is wrong: shape {tuple(render.shape)}, alpha max {float(alpha.max())}")
        found["render_s"] = round(time.perf_counter() - start, 3)
except Exception as error:
    found["error"] = f"{type(error).__name__}: {error}"
    done(1)
done(0)
"""


# --------------------------------------------------------------------------- running it


def setup_environment() -> dict[str, str]:
    """The environment of the set-up's commands: ours without the variables that would make
    another Python import Blender's modules or the caller's packages."""
    env = dict(os.environ)
    for name in ("PYTHONHOME", "PYTHONPATH", "PYTHONSTARTUP", "PYTHONNOUSERSITE", "VIRTUAL_ENV", "PIP_USER",
                 "PIP_TARGET", "PIP_PREFIX", "PIP_REQUIRE_VIRTUALENV"):
        env.pop(name, None)
    env["PYTHONUNBUFFERED"] = "1"
    env["PIP_NO_INPUT"] = "1"
    return env


def _stop(process: subprocess.Popen) -> None:
    if process.poll() is not None:
        return
    process.terminate()
    try:
        process.wait(timeout=5)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def run_command(command: SetupCommand, *, on_line: Callable[[str], None], cancel: Optional[threading.Event] = None,
                env: Optional[dict[str, str]] = None, cwd: Optional[Path] = None,
                tail: Optional[collections.deque] = None) -> int:
    """Run one step, passing each line it prints to ``on_line``; returns its exit status.

    Raises :class:`SetupCancelled` as soon as ``cancel`` is set (the process is stopped):
    output is read on a thread, so a step that prints nothing for minutes (a download)
    is still cancelled at once."""
    try:
        process = subprocess.Popen(command.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                   stdin=subprocess.DEVNULL, text=True, encoding="utf-8", errors="replace",
                                   env=env if env is not None else setup_environment(), cwd=cwd)
    except OSError as error:
        raise TrainerSetupError(f"{command.label}: cannot run {command.argv[0]}: {error}") from error
    lines: queue.Queue = queue.Queue()

    def read() -> None:
        for line in process.stdout:
            lines.put(line.rstrip("\r\n"))
        lines.put(None)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        while True:
            if cancel is not None and cancel.is_set():
                _stop(process)
                raise SetupCancelled("the trainer set-up was cancelled; nothing was kept")
            try:
                line = lines.get(timeout=0.1)
            except queue.Empty:
                continue
            if line is None:
                break
            if tail is not None:
                tail.append(line)
            on_line(line)
    finally:
        _stop(process)
        reader.join(timeout=5)
        process.stdout.close()
    return process.returncode


def _failure(command: SetupCommand, returncode: int, output: Sequence[str]) -> TrainerSetupError:
    text = "\n".join(output)
    last = next((line.strip() for line in reversed(output) if line.strip()), "no output")[:200]
    if command.kind in ("torch", "requirements"):
        if any(marker in text for marker in _UNREACHABLE_MARKERS):
            return TrainerSetupError(f"{command.label}: the package index could not be reached ({last})",
                                     hint=OFFLINE_HINT)
        if any(marker in text for marker in _NOT_FOUND_MARKERS):
            return TrainerSetupError(f"{command.label}: a package was not found ({last})", hint=OFFLINE_HINT)
    if command.kind == "venv":
        return TrainerSetupError(f"{command.label} failed ({last})",
                                 hint="the Python that creates the environment must be 3.11 with venv and "
                                      "ensurepip (Blender's own Python has both)")
    return TrainerSetupError(f"{command.label} failed with exit status {returncode} ({last})")


def _verify_result(output: Sequence[str]) -> dict:
    for line in reversed(output):
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                break
    return {}


def check_trainer(python: str | os.PathLike, *, render: bool = False, timeout_s: float = 300) -> dict:
    """What a trainer Python has: its interpreter and prefix, the versions of torch, numpy and
    the other requirements, CUDA (device), where the engine is imported from, and ``error`` when
    something is missing. ``render`` also renders a few Gaussians (seconds: Numba compiles)."""
    modules = sorted(set(REQUIREMENT_MODULES.values()))
    try:
        done = subprocess.run([str(python), "-c", VERIFY_SCRIPT, "render" if render else "check", *modules],
                              capture_output=True, text=True, timeout=timeout_s, env=setup_environment(),
                              cwd=tempfile.gettempdir(), stdin=subprocess.DEVNULL)
    except (OSError, subprocess.TimeoutExpired) as error:
        return {"python": str(python), "error": f"{type(error).__name__}: {error}"}
    found = _verify_result(done.stdout.splitlines())
    if not found:
        found = {"python": str(python), "error": (done.stderr.strip().splitlines() or ["no output"])[-1]}
    return found


def describe(found: dict) -> list[str]:
    """Lines for the UI and the console from :func:`check_trainer`'s answer."""
    lines = [f"Python {found.get('version', '?')}: {found.get('python', '?')}"]
    if found.get("torch"):
        backend = f"CUDA {found.get('cuda_version')} on {found.get('device')}" if found.get("cuda") else \
            "CPU" + (" (Apple GPU via MPS available)" if found.get("mps") else "")
        lines.append(f"torch {found['torch']}, numpy {found.get('numpy', '?')}; backend: {backend}")
    if found.get("engine"):
        lines.append(f"engine {found.get('engine_version', '')}: {found['engine']}")
    if found.get("render_s") is not None:
        lines.append(f"test render: {found['render_s']:.2f} s")
    if found.get("error"):
        lines.append(f"problem: {found['error']}")
    return lines


def _remove(path: Path) -> None:
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.exists():
        shutil.rmtree(path, ignore_errors=True)


def remove_environment(env_dir: str | os.PathLike) -> bool:
    """Delete the set-up environment (and leftovers of interrupted set-ups); True if there was one."""
    env_dir = Path(env_dir)
    existed = env_dir.exists()
    _remove(env_dir)
    for leftover in env_dir.parent.glob(f".{env_dir.name}-*") if env_dir.parent.is_dir() else ():
        _remove(leftover)
    return existed


def run_setup(target_dir: str | os.PathLike, *, python: str | os.PathLike | None = None, variant: str = "cpu",
              find_links: str | os.PathLike | Iterable[str | os.PathLike] | None = None,
              index_url: Optional[str] = None, requirements: str | os.PathLike | None = None,
              engine_dir: str | os.PathLike = PACKAGE_ROOT, system_site_packages: bool = False,
              on_line: Callable[[str], None] = print, cancel: Optional[threading.Event] = None,
              planner: Optional[Callable[[Path], list[SetupCommand]]] = None) -> dict:
    """Build the trainer environment at ``target_dir``; return :func:`check_trainer`'s answer
    for it (the verify step's).

    The environment is built in a hidden sibling folder (``.trainer-building-*``) and renamed
    to ``target_dir`` only when the verify step passed; an existing environment is replaced
    then, not before. On a failure or a cancel the building folder is removed and
    ``target_dir`` is untouched. Each line the commands print goes to ``on_line`` (step
    headings start with ``"==> "``). ``planner`` makes the plan for a building folder
    (default :func:`plan_setup` with these arguments; tests pass failing commands).

    Raises:
        TrainerSetupError: a step failed (the index unreachable: the message says what to do).
        SetupCancelled: ``cancel`` was set.
    """
    target = Path(target_dir).absolute()
    python = str(python or sys.executable)
    if planner is None:
        def planner(folder: Path) -> list[SetupCommand]:
            return plan_setup(folder, python=python, variant=variant, find_links=find_links, index_url=index_url,
                              requirements=requirements, engine_dir=engine_dir,
                              system_site_packages=system_site_packages)
    target.parent.mkdir(parents=True, exist_ok=True)
    building = Path(tempfile.mkdtemp(prefix=f".{target.name}-building-", dir=target.parent))
    building.rmdir()  # venv creates it; the name stays ours (mkdtemp picked a free one)
    previous: Optional[Path] = None
    try:
        commands = planner(building)
        env = setup_environment()
        found: dict = {}
        started = time.monotonic()
        for number, command in enumerate(commands, start=1):
            on_line(f"==> [{number}/{len(commands)}] {command.label}")
            output: collections.deque = collections.deque(maxlen=200)
            returncode = run_command(command, on_line=on_line, cancel=cancel, env=env, cwd=target.parent,
                                     tail=output)
            if command.kind == "verify":
                found = _verify_result(output)
                if returncode != 0 or found.get("error"):
                    raise TrainerSetupError(f"the new environment does not work: "
                                            f"{found.get('error') or (list(output) or ['no output'])[-1]}")
            elif returncode != 0:
                raise _failure(command, returncode, list(output))
        if cancel is not None and cancel.is_set():
            raise SetupCancelled("the trainer set-up was cancelled; nothing was kept")
        if target.exists():
            previous = target.parent / f".{target.name}-previous-{os.getpid()}"
            _remove(previous)
            target.rename(previous)
        building.rename(target)
        if previous is not None:
            _remove(previous)
            previous = None
        found["python"] = str(venv_python(target))
        found["prefix"] = str(target)
        on_line(f"==> Trainer ready in {time.monotonic() - started:.0f} s: {found['python']}")
        return found
    except BaseException:
        _remove(building)
        if previous is not None and previous.exists() and not target.exists():
            previous.rename(target)  # the earlier environment back, as it was
        raise


# --------------------------------------------------------------------------- in the background


class SetupJob:
    """:func:`run_setup` on a thread, for a UI that polls: ``lines`` (the latest output),
    ``status`` (``running``, ``finished``, ``failed``, ``cancelled``), ``error``, ``result``."""

    def __init__(self, target_dir: str | os.PathLike, *, max_lines: int = 400, **options):
        self.target_dir = Path(target_dir)
        self.options = options
        self.lines: collections.deque[str] = collections.deque(maxlen=max_lines)
        self.step = ""
        self.status = "running"
        self.error = ""
        self.result: dict = {}
        self.started_at = time.monotonic()
        self.ended_at: Optional[float] = None
        self._cancel = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="esgs-trainer-setup", daemon=True)

    def start(self) -> "SetupJob":
        self._thread.start()
        return self

    def _line(self, line: str) -> None:
        with self._lock:
            self.lines.append(line)
            if line.startswith("==> "):
                self.step = line[4:]

    def _run(self) -> None:
        try:
            result = run_setup(self.target_dir, on_line=self._line, cancel=self._cancel, **self.options)
        except SetupCancelled as error:
            self._end("cancelled", str(error))
        except ESGSError as error:
            self._end("failed", str(error))
        except Exception as error:  # a bug must still end the job, visibly
            self._end("failed", f"{type(error).__name__}: {error}")
        else:
            self.result = result
            self._end("finished", "")

    def _end(self, status: str, error: str) -> None:
        with self._lock:
            self.error = error
            if error:
                self.lines.append(error)
            self.ended_at = time.monotonic()
            self.status = status

    @property
    def active(self) -> bool:
        return self.status == "running"

    @property
    def elapsed_s(self) -> float:
        return (self.ended_at or time.monotonic()) - self.started_at

    def tail(self, count: int) -> list[str]:
        with self._lock:
            return list(self.lines)[-count:]

    def cancel(self) -> None:
        self._cancel.set()

    def wait(self, timeout: Optional[float] = None) -> bool:
        """Wait for the end; True when it ended."""
        self._thread.join(timeout)
        return not self._thread.is_alive()


def format_elapsed(seconds: float) -> str:
    """``75`` -> ``"1:15"``."""
    minutes, secs = divmod(int(seconds), 60)
    return f"{minutes}:{secs:02d}"
