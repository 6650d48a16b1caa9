"""Issue #24's acceptance: Blender from the zip alone.

The zip ``esgs build-extension`` makes (Linux, the default; about a second with its wheels
cached, as ``tests/test_extension_package.py`` needs them too) is installed into a fresh Blender user profile
under the bpy module, in a process that has no checkout on its path, no ``PYTHONPATH`` and
no ``ESGS_PYTHON`` (``zip_end_to_end.py``, run in a subprocess since bpy reads the profile's
environment variables at import). There *Set Up Trainer* builds the trainer environment in
the extension's user directory from a local wheel folder (offline), and the panel's
operators run in order: Generate -> Render Dataset -> Compute Priors (NDN) -> Train (30
steps, headless: blocking) -> Import Gaussians -> Compare to Mesh.

The wheel folder is the stand-in of ``test_trainer_setup.py``'s real set-up: instead of the
heavy wheels (torch alone is hundreds of MB, and the network is not ours to use in tests),
one tiny metadata-only wheel per pinned requirement that the zip does not bundle (torch,
numpy, numba, tqdm), at the pinned version; the torch one carries a ``.pth`` file that puts
this suite's ``site-packages`` on the new environment's path (where those modules really
are), and a line that appends each start of a Python of that environment to a trace file.
The set-up's requirements step is offered the zip's own ``wheels/`` folder (scipy, OpenCV,
OpenEXR, trimesh, pycolmap), as for a user, but finds those already satisfied through the
stand-in's path, so installing them is not covered here; nor are downloading torch, choosing
a torch index, Windows and macOS.

The trace shows the priors and training children ran with the set-up environment's Python
and imported the engine from the installed extension, not the checkout.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import time
import zipfile
from pathlib import Path

import pytest

pytest.importorskip("bpy", reason="the bpy module is not installed")

from esgs.core.apps import packaging  # noqa: E402
from esgs.core.formats.ply import read_gaussians_ply  # noqa: E402
from esgs.esgs_addon import trainer_setup  # noqa: E402
from tests.blender.test_trainer_setup import _record_line  # noqa: E402


REPO_ROOT = packaging.REPO_ROOT
SITE_PACKAGES = Path(sysconfig.get_paths()["purelib"])
DRIVER = Path(__file__).with_name("zip_end_to_end.py")

#: the .pth line of the stand-in torch wheel: every Python of the environment appends, as it
#: exits, its interpreter, the file of the ``esgs`` it imported ("-": none) and its command line
#: to $ESGS_E2E_TRACE (when set)
TRACE_LINE = ('import atexit, os, sys; _esgs_trace = os.environ.get("ESGS_E2E_TRACE"); _esgs_trace and atexit.register('
              'lambda path=_esgs_trace, command=open("/proc/self/cmdline").read().replace("\\0", " ")'
              '.replace("\\n", " "): open(path, "a").write("\\t".join([sys.executable, getattr(sys.modules.get('
              '"esgs"), "__file__", None) or "-", command]) + "\\n"))')


def build_wheel(folder: Path, name: str, version: str, files: dict[str, bytes]) -> Path:
    """A pure-Python wheel ``name==version`` holding ``files``."""
    dist = name.replace("-", "_")
    files = {**files,
             f"{dist}-{version}.dist-info/METADATA": f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n".encode(),
             f"{dist}-{version}.dist-info/WHEEL": b"Wheel-Version: 1.0\nGenerator: esgs-tests\nRoot-Is-Purelib: true\n"
                                                  b"Tag: py3-none-any\n"}
    record = f"{dist}-{version}.dist-info/RECORD"
    path = folder / f"{dist}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(path, "w") as wheel:
        for member, data in files.items():
            wheel.writestr(member, data)
        wheel.writestr(record, "\n".join([_record_line(p, d) for p, d in files.items()] + [f"{record},,"]) + "\n")
    return path


def stand_in_wheels(folder: Path, extension_zip: Path) -> list[str]:
    """The wheel folder: a stand-in for each requirement the zip does not bundle; returns their names."""
    folder.mkdir(parents=True)
    with zipfile.ZipFile(extension_zip) as archive:
        requirements = Path(archive.extract(trainer_setup.REQUIREMENTS_NAME, folder.parent / "shipped"))
        bundled = {Path(name).name.split("-")[0].lower().replace("_", "-") for name in archive.namelist()
                   if name.startswith("wheels/") and name.endswith(".whl")}
    made = []
    for line in trainer_setup.read_requirements(requirements):
        name = trainer_setup.requirement_name(line)
        if name in bundled:
            continue
        version = line.split("==", 1)[1]
        files = {"esgs_e2e_site.pth": f"{SITE_PACKAGES}\n{TRACE_LINE}\n".encode()} if name == "torch" else {}
        build_wheel(folder, name, version, files)
        made.append(name)
    return made


def clean_environment(profile: Path, home: Path, trace: Path) -> dict[str, str]:
    """A new user's environment: a fresh Blender profile and home, no PYTHONPATH or ESGS_PYTHON,
    no folder of the checkout on PATH."""
    path = os.pathsep.join(p for p in os.environ.get("PATH", "/usr/bin:/bin").split(os.pathsep)
                           if p and not Path(p).resolve().is_relative_to(REPO_ROOT))
    env = {"PATH": path, "HOME": str(home), "LANG": "C.UTF-8", "TMPDIR": str(home),
           "BLENDER_USER_RESOURCES": str(profile), "BLENDER_USER_CONFIG": str(profile / "config"),
           "BLENDER_USER_SCRIPTS": str(profile / "scripts"), "ESGS_E2E_TRACE": str(trace),
           "OMP_WAIT_POLICY": "PASSIVE"}
    return env


def test_blenders_python_in_some_venv_is_not_called_the_checkouts(tmp_path, monkeypatch):
    """An installed extension has no .venv of its own: with no trainer set up, the trainer is
    Blender's own Python, even when that Python lives in a virtual environment (the bpy module
    installed with pip, as here), which the label used to call "the checkout's .venv"."""
    from esgs.core.runtime import process
    from esgs.esgs_addon import preferences

    extension = tmp_path / "extensions" / "user_default" / "esgs"
    extension.mkdir(parents=True)
    monkeypatch.delenv("ESGS_PYTHON", raising=False)
    monkeypatch.setattr(process, "_PACKAGE_ROOT", extension)
    monkeypatch.setattr(trainer_setup, "PACKAGE_ROOT", extension)
    monkeypatch.setattr(preferences, "environment_dir", lambda create=False: tmp_path / "not_set_up")
    assert preferences.trainer_choice() == (sys.executable, "Blender's own Python")
    # a checkout's own .venv keeps its name
    venv_python = trainer_setup.venv_python(extension / ".venv")
    venv_python.parent.mkdir(parents=True)
    venv_python.write_text("")
    assert preferences.trainer_choice() == (str(venv_python), "the checkout's .venv")


@pytest.mark.slow
@pytest.mark.skipif(sys.platform != "linux", reason="the Linux zip end to end")
def test_the_zip_alone_sets_up_a_trainer_and_runs_the_whole_flow(tmp_path):
    from esgs.core.cli import main

    started = time.perf_counter()
    assert main(["build-extension", "--out", str(tmp_path / "dist")]) == 0  # the Linux zip by default
    build_s = time.perf_counter() - started
    extension_zip, = (tmp_path / "dist").glob("*.zip")
    wheels = tmp_path / "wheels"
    assert sorted(stand_in_wheels(wheels, extension_zip)) == ["numba", "numpy", "torch", "tqdm"]
    profile, home, work, trace = tmp_path / "profile", tmp_path / "home", tmp_path / "work", tmp_path / "trace.txt"
    for folder in (profile, home, work):
        folder.mkdir()
    done = subprocess.run([sys.executable, "-S", str(DRIVER), str(extension_zip), str(SITE_PACKAGES), str(wheels),
                           str(work)], cwd=work, env=clean_environment(profile, home, trace),
                          capture_output=True, text=True, timeout=900)
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-6000:]
    found = json.loads(done.stdout.strip().splitlines()[-1])
    print("zip end to end:", f"build {build_s:.1f} s", found["timings_s"], found["reports"], sep="\n  ")
    reports = found["reports"]

    # installed from the zip, never imported from the checkout
    assert not found["esgs_before_install"]
    assert not any(Path(p).resolve() == REPO_ROOT for p in found["sys_path"])
    assert found["install"] == ["FINISHED"]
    extension = profile / "extensions" / "user_default" / "esgs"
    assert found["addon_file"] == str(extension / "__init__.py")
    assert found["addon_enabled"] and found["addon_loaded"] == [True, True]
    assert found["plain_esgs_modules"] == [] and found["engine_modules_outside_extension"] == []
    assert not Path(found["cwd"]).resolve().is_relative_to(REPO_ROOT)

    # Set Up Trainer: before it, Blender's own Python (no checkout .venv to fall back on); after,
    # the environment it made in the extension's user directory
    assert found["trainer_before"][1] == "Blender's own Python", found["trainer_before"]
    assert reports["trainer_setup"] == ["FINISHED"], output[-6000:]
    environment = profile / "extensions" / ".user" / "user_default" / "esgs" / "trainer"
    python = environment / "bin" / "python"
    assert found["environment_dir"] == str(environment)
    assert found["trainer_after"] == [str(python), "Set Up Trainer"]
    assert any(line.startswith("torch 2.") and "backend: CPU" in line for line in found["setup_check"])
    assert any(line.startswith("engine ") and str(extension) in line for line in found["setup_check"]), \
        found["setup_check"]
    purelib = next(environment.glob("lib/python3*/site-packages"))
    assert (purelib / trainer_setup.ENGINE_PTH_NAME).read_text().strip() == str(extension.parent)
    started_by = [line.split("\t") for line in trace.read_text().splitlines()]
    pip_requirements = [command for _, _, command in started_by if " -m pip install " in command and " -r " in command]
    assert pip_requirements and all(f"--find-links {extension / 'wheels'} " in command for command in
                                    pip_requirements), pip_requirements  # the zip's wheels offered to pip

    # Generate -> Render Dataset: the rendered folder becomes the training's scene
    scene = work / "scene"
    assert reports["generate_terrain"] == ["FINISHED"] and reports["render_dataset"] == ["FINISHED"], reports
    assert found["training_scene_dir"] == str(scene)
    assert len(list((scene / "images").iterdir())) == 4
    assert (scene / "mesh" / "ground_truth.ply").is_file()

    # Compute Priors (NDN) with the set-up trainer
    assert found["priors_poll"] and reports["compute_priors"] == ["FINISHED"], (reports, found["priors_state"])
    priors = scene / "priors" / "ndn"
    assert priors.is_dir() and len([p for p in priors.rglob("*") if p.is_file()]) >= 4

    # Train 30 steps; the run folder's Gaussians read back
    run = work / "run"
    assert reports["train"] == ["FINISHED"], (reports, found["training_state"])
    assert found["training_state"][0] == "finished" and found["training_state"][3] == 30
    assert found["training_command"][:3] == [str(python), "-m", "esgs.core.runtime.child"]
    ply = read_gaussians_ply(run / "point_cloud.ply")
    n_gaussians = len(ply.means)
    assert n_gaussians > 0
    assert json.loads((run / "config.json").read_text())["scene"] == str(scene)

    # the children ran with the set-up environment's Python and its engine from the extension
    children = [(executable, engine, command) for executable, engine, command in started_by
                if "esgs.core.runtime.child" in command]
    assert any(" priors " in command for _, _, command in children), children
    assert any(" train " in command for _, _, command in children), children
    assert {(executable, engine) for executable, engine, _ in children} == {
        (str(python), str(extension / "__init__.py"))}, children

    # Import: Train imported its result, and File > Import Gaussians reads the same file
    assert found["trained_object"] is not None and found["trained_object"][2] == n_gaussians, found["trained_object"]
    assert reports["import_gaussians"] == ["FINISHED"]
    assert found["imported_object"][1:] == ["POINTCLOUD", n_gaussians]

    # Compare to Mesh against the generated terrain: finite distances of the right size, and
    # recall over the surface the run's cameras saw
    assert reports["compare_to_mesh"] == ["FINISHED"], reports
    compare = found["compare"]
    assert compare["finite"] and compare["n_gaussians"] == n_gaussians, compare
    assert compare["n_gaussians_filtered"] == n_gaussians  # Opacity min 0: 30 steps leave them faint
    assert compare["distances"]["median"] < compare["threshold_m"], compare
    assert compare["precision"] > 0.9 and 0.0 < compare["recall"] <= 1.0 and compare["fscore"] > 0.0, compare
    assert compare["recall_scope"] == "surface seen by the training cameras", compare
    assert compare["cameras"].startswith("3 training views"), compare  # 4 views, every 4th held out
