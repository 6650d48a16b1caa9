"""Setting up the trainer environment (esgs_addon/trainer_setup.py): the plan, atomicity on
failure and cancel, and one real set-up on Linux from a local wheel folder with no network.

What the end-to-end test covers and what it does not: it really creates a virtual environment
with ``python -m venv`` (pip through ensurepip), really runs ``pip install --no-index
--find-links WHEELS`` into it, installs the engine from an extension-shaped folder
(``.../user_default/esgs``) through the ``.pth`` file, renames the verified environment into
place, and renders a few Gaussians with it from a clean environment (no PYTHONPATH). To stay
fast and offline, the local wheel folder holds one small wheel we build here whose ``.pth`` file
puts the test suite's own ``site-packages`` (torch, numpy, numba, ...) on the new environment's
path (installed by one step the test adds before the plan's requirements step, whose
requirements file then names only that wheel). So it does *not* download or install torch or
the pinned set, nor choose a torch index for real; the plan tests check the pip options, and
``test_trainer_requirements_match_the_tested_set`` checks the pinned set against the suite's
environment.
"""
from __future__ import annotations

import base64
import hashlib
import os
import subprocess
import sys
import sysconfig
import threading
import time
import zipfile
from pathlib import Path

import pytest

from esgs.esgs_addon import trainer_setup
from esgs.esgs_addon.trainer_setup import SetupCommand, SetupJob, TrainerSetupError, plan_setup, run_setup

REPO_ROOT = trainer_setup.PACKAGE_ROOT
SITE_PACKAGES = Path(sysconfig.get_paths()["purelib"])


def pip_options(command: SetupCommand) -> list[str]:
    return list(command.argv[command.argv.index("install"):])


# --------------------------------------------------------------------------- the plan


def test_plan_cpu_installs_torch_first_from_the_cpu_index(tmp_path):
    plan = plan_setup(tmp_path / "env", python="/blender/python3.11", variant="cpu")
    assert [c.kind for c in plan] == ["venv", "torch", "requirements", "engine", "verify"]
    assert plan[0].argv == ("/blender/python3.11", "-m", "venv", str(tmp_path / "env"))
    python = str(tmp_path / "env" / "bin" / "python")
    assert all(c.argv[0] == python for c in plan[1:])
    torch = pip_options(plan[1])
    assert "torch==2.13.0" in torch and "-r" not in torch
    assert torch[torch.index("--index-url") + 1] == "https://download.pytorch.org/whl/cpu"
    requirements = pip_options(plan[2])
    assert requirements[requirements.index("-r") + 1] == str(REPO_ROOT / "requirements-trainer.txt")
    assert "--index-url" not in requirements and "--no-index" not in requirements  # the rest from PyPI
    assert plan[3].argv[-1] == str(REPO_ROOT)
    assert {"cv2", "OpenEXR", "numba", "pycolmap", "torch", "trimesh"} <= set(plan[4].argv[4:])


def test_plan_cuda_uses_a_cuda_index_and_a_wheel_folder_means_offline(tmp_path):
    cuda = plan_setup(tmp_path / "env", python="py", variant="cuda")
    options = pip_options(cuda[1])
    assert options[options.index("--index-url") + 1] == trainer_setup.TORCH_INDEX["cuda"]
    assert "/cu" in trainer_setup.TORCH_INDEX["cuda"]

    wheels = tmp_path / "wheels"
    wheels.mkdir()
    for step in plan_setup(tmp_path / "env", python="py", variant="cuda", find_links=wheels)[1:3]:
        options = pip_options(step)
        assert options[options.index("--find-links") + 1] == str(wheels)
        assert "--no-index" in options and "--index-url" not in options

    mirror = plan_setup(tmp_path / "env", python="py", variant="cpu", find_links=[wheels],
                        index_url="https://mirror.example/simple")
    for step in mirror[1:3]:
        options = pip_options(step)
        assert options[options.index("--index-url") + 1] == "https://mirror.example/simple"
        assert "--no-index" not in options and "--find-links" in options


def test_plan_offers_the_extensions_bundled_wheels_and_rejects_bad_input(tmp_path):
    engine = tmp_path / "esgs"
    (engine / "wheels").mkdir(parents=True)
    (engine / "requirements-trainer.txt").write_text("# comment\nnumpy==1.26.4  # pinned\n\n")
    plan = plan_setup(tmp_path / "env", python="py", variant="cpu", engine_dir=engine)
    assert [c.kind for c in plan] == ["venv", "requirements", "engine", "verify"]  # no torch line, no torch step
    options = pip_options(plan[1])
    assert options[options.index("--find-links") + 1] == str(engine / "wheels") and "--no-index" not in options
    assert plan_setup(tmp_path / "env", python="py", variant="cpu", engine_dir=engine,
                      system_site_packages=True)[0].argv[3] == "--system-site-packages"
    with pytest.raises(TrainerSetupError, match="unknown torch build"):
        plan_setup(tmp_path / "env", python="py", variant="rocm", engine_dir=engine)
    with pytest.raises(TrainerSetupError, match="wheel folder does not exist"):
        plan_setup(tmp_path / "env", python="py", variant="cpu", engine_dir=engine, find_links=tmp_path / "nope")
    with pytest.raises(TrainerSetupError, match="requirements file cannot be read"):
        plan_setup(tmp_path / "env", python="py", variant="cpu", engine_dir=tmp_path)


def test_variant_detection_and_venv_paths():
    assert trainer_setup.detect_variant(lambda name: "/usr/bin/nvidia-smi", "linux")[0] == "cuda"
    assert trainer_setup.detect_variant(lambda name: None, "linux")[0] == "cpu"
    assert trainer_setup.detect_variant(lambda name: "/x/nvidia-smi", "darwin")[0] == "cpu"
    assert trainer_setup.venv_python("/e", windows=True) == Path("/e/Scripts/python.exe")
    assert trainer_setup.venv_python("/e", windows=False) == Path("/e/bin/python")


def test_trainer_requirements_match_the_tested_set():
    """Every trainer requirement is pinned, has a module the check imports, and is the version
    the test suite runs with (so the trainer gets what was tested)."""
    from importlib import metadata

    lines = trainer_setup.read_requirements(REPO_ROOT / "requirements-trainer.txt")
    names = [trainer_setup.requirement_name(line) for line in lines]
    assert "torch" in names and not {"bpy", "ray", "pytest", "ruff", "hypothesis"} & set(names)
    for line, name in zip(lines, names):
        assert "==" in line, f"{line}: not pinned"
        assert name in trainer_setup.REQUIREMENT_MODULES, name
        assert metadata.version(name).split("+")[0] == line.split("==")[1], line


def test_every_third_party_import_of_the_engine_is_a_requirement():
    """The engine's imports (core/, outside the optional CUDA / Ray / Blender parts) are all in
    the trainer's requirements."""
    import ast

    optional = {"gsplat", "ray", "bpy", "lpips", "matplotlib", "gsply"}  # CUDA backend, esgs bench, Blender children, optional metric, the report's plots (OpenCV without it), esgs export --format spz
    provided = set(trainer_setup.REQUIREMENT_MODULES.values()) | set(sys.stdlib_module_names) | {"esgs"}
    missing = {}
    for path in (REPO_ROOT / "core").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else []
            for name in names:
                top = name.split(".")[0]
                if top not in provided | optional:
                    missing.setdefault(top, str(path.relative_to(REPO_ROOT)))
    assert not missing, missing


# --------------------------------------------------------------------------- nothing half-made


def fake_plan(tmp_path: Path, script: str) -> callable:
    """A planner whose first step makes the building folder (as venv would) and whose second
    is a "pip" that runs ``script``."""
    fake_pip = tmp_path / "fake_pip.py"
    fake_pip.write_text(script)

    def planner(folder: Path) -> list[SetupCommand]:
        return [SetupCommand("venv", "make the folder", (sys.executable, "-c",
                                                         "import os, sys; os.makedirs(sys.argv[1] + '/bin')",
                                                         str(folder))),
                SetupCommand("requirements", "fake pip", (sys.executable, str(fake_pip), str(folder)))]
    return planner


def leftovers(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith(".trainer") or p.name == "trainer")


def test_a_failing_install_leaves_nothing_and_keeps_an_earlier_environment(tmp_path):
    user_dir = tmp_path / "user"
    lines = []
    script = "import sys; open(sys.argv[1] + '/half.txt', 'w').write('x'); print('Collecting torch'); sys.exit(3)"
    with pytest.raises(TrainerSetupError, match="fake pip failed with exit status 3"):
        run_setup(user_dir / "trainer", on_line=lines.append, planner=fake_plan(tmp_path, script))
    assert leftovers(user_dir) == []
    assert "Collecting torch" in lines and lines[0].startswith("==> [1/2]")

    earlier = user_dir / "trainer"
    (earlier / "bin").mkdir(parents=True)
    (earlier / "bin" / "python").write_text("earlier")
    with pytest.raises(TrainerSetupError):
        run_setup(earlier, on_line=lines.append, planner=fake_plan(tmp_path, script))
    assert leftovers(user_dir) == ["trainer"] and (earlier / "bin" / "python").read_text() == "earlier"


def test_an_unreachable_index_says_what_to_do(tmp_path):
    script = ("print(\"WARNING: Retrying after connection broken by 'NewConnectionError(...): Failed to establish a "
              "new connection: [Errno -3] Temporary failure in name resolution')\")\n"
              "print('ERROR: No matching distribution found for torch==2.13.0'); raise SystemExit(1)")
    with pytest.raises(TrainerSetupError) as caught:
        run_setup(tmp_path / "user" / "trainer", on_line=lambda line: None, planner=fake_plan(tmp_path, script))
    message = str(caught.value)
    assert "package index could not be reached" in message
    assert "Trainer Python" in message and "Wheel Folder" in message
    assert leftovers(tmp_path / "user") == []


def test_cancel_stops_a_silent_step_and_leaves_nothing(tmp_path):
    script = "import sys, time; open(sys.argv[1] + '/half.txt', 'w'); print('Downloading', flush=True); time.sleep(60)"
    job = SetupJob(tmp_path / "user" / "trainer", planner=fake_plan(tmp_path, script)).start()
    deadline = time.monotonic() + 30
    while "Downloading" not in job.tail(5) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert job.active and "fake pip" in job.step
    started = time.monotonic()
    job.cancel()
    assert job.wait(timeout=15)
    assert time.monotonic() - started < 10  # not the step's 60 s
    assert job.status == "cancelled" and "cancelled" in job.error
    assert leftovers(tmp_path / "user") == []


def test_a_working_environment_that_fails_its_check_is_not_kept(tmp_path):
    def planner(folder):
        return [SetupCommand("venv", "make", (sys.executable, "-c", "import os,sys; os.makedirs(sys.argv[1])",
                                              str(folder))),
                SetupCommand("verify", "check", (sys.executable, "-c", trainer_setup.VERIFY_SCRIPT, "check",
                                                 "no_such_module_xyz"))]
    job = SetupJob(tmp_path / "user" / "trainer", planner=planner).start()
    assert job.wait(timeout=120)
    assert job.status == "failed" and "no_such_module_xyz" in job.error
    assert leftovers(tmp_path / "user") == []


# --------------------------------------------------------------------------- the real thing (Linux)


def _record_line(path: str, data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{path},sha256={digest},{len(data)}"


def build_site_wheel(folder: Path, site_packages: Path) -> str:
    """A tiny wheel ``esgs_test_site`` whose .pth puts ``site_packages`` on the path (a stand-in
    for the heavy wheels, see the module docstring); returns its requirement line."""
    name, version = "esgs_test_site", "1.0"
    files = {
        f"{name}.pth": f"{site_packages}\n".encode(),
        f"{name}-{version}.dist-info/METADATA": f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n".encode(),
        f"{name}-{version}.dist-info/WHEEL": b"Wheel-Version: 1.0\nGenerator: esgs-tests\nRoot-Is-Purelib: true\n"
                                             b"Tag: py3-none-any\n",
    }
    record = f"{name}-{version}.dist-info/RECORD"
    with zipfile.ZipFile(folder / f"{name}-{version}-py3-none-any.whl", "w") as wheel:
        for path, data in files.items():
            wheel.writestr(path, data)
        wheel.writestr(record, "\n".join([_record_line(p, d) for p, d in files.items()] + [f"{record},,"]) + "\n")
    return f"esgs-test-site=={version}"


@pytest.mark.skipif(sys.platform != "linux", reason="the Linux set-up end to end")
def test_set_up_a_real_environment_offline_and_render_with_it(tmp_path):
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    requirement_lines = [build_site_wheel(wheels, SITE_PACKAGES)]
    requirements = tmp_path / "requirements.txt"
    requirements.write_text("\n".join(requirement_lines) + "\n")
    # an installed extension: .../extensions/user_default/esgs (here a link to the checkout)
    repository = tmp_path / "extensions" / "user_default"
    repository.mkdir(parents=True)
    (repository / "esgs").symlink_to(REPO_ROOT, target_is_directory=True)
    user_dir = tmp_path / "extensions" / ".user" / "user_default" / "esgs"

    def planner(folder: Path) -> list[SetupCommand]:
        """The real plan, and one step before the requirements: the stand-in wheel, so the
        requirements' dependencies (numpy for trimesh) are met from the suite's site-packages."""
        plan = plan_setup(folder, python=sys.executable, variant="cpu", find_links=wheels, requirements=requirements,
                          engine_dir=repository / "esgs")
        assert [c.kind for c in plan] == ["venv", "requirements", "engine", "verify"]
        stand_in = SetupCommand("requirements", "the test's stand-in for the heavy wheels",
                                (plan[1].argv[0], "-m", "pip", "install", "--no-index", "--find-links", str(wheels),
                                 requirement_lines[0]))
        return [plan[0], stand_in, *plan[1:]]

    lines = []
    found = run_setup(user_dir / "trainer", on_line=lines.append, planner=planner)
    text = "\n".join(lines)
    assert "Successfully installed esgs-test-site-1.0" in text
    python = user_dir / "trainer" / "bin" / "python"
    assert found["python"] == str(python) and python.is_file()
    assert found["engine"] == str(repository / "esgs") or Path(found["engine"]).resolve() == REPO_ROOT
    assert found["torch"].startswith("2.") and found["render_s"] >= 0 and not found.get("error")
    assert leftovers(user_dir) == ["trainer"]
    pth = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                              capture_output=True, text=True, check=True).stdout.strip()) / "esgs_engine.pth"
    assert pth.read_text().strip() == str(repository)
    assert "Requirement already satisfied: esgs-test-site==1.0" in text  # the plan's requirements step, offline

    # the renamed environment works on its own: a fresh process, no PYTHONPATH, imports the engine
    # from the extension folder under the name the child process uses
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    done = subprocess.run([str(python), "-c", "import sys, esgs, esgs.core.runtime.child, torch; "
                                              "print(sys.prefix); print(esgs.__file__)"],
                          capture_output=True, text=True, env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    prefix, engine_file = done.stdout.split()
    assert prefix == str(user_dir / "trainer")
    assert engine_file == str(repository / "esgs" / "__init__.py")
    checked = trainer_setup.check_trainer(python)
    assert checked["torch"] == found["torch"] and not checked.get("error")
    assert any("torch" in line and "backend: CPU" in line for line in trainer_setup.describe(checked))

    # set up again over it: replaced only when the new one is verified; then removed
    stop = threading.Event()
    stop.set()
    with pytest.raises(trainer_setup.SetupCancelled):
        run_setup(user_dir / "trainer", find_links=wheels, requirements=requirements,
                  engine_dir=repository / "esgs", on_line=lines.append, cancel=stop)
    assert leftovers(user_dir) == ["trainer"] and python.is_file()
    assert trainer_setup.remove_environment(user_dir / "trainer")
    assert leftovers(user_dir) == []
