"""The driver of ``test_zip_end_to_end.py``: a new Blender user's session with only the zip.

Run as ``python -S zip_end_to_end.py ZIP SITE_PACKAGES WHEELS WORK`` in a clean environment
(``BLENDER_USER_RESOURCES`` / ``BLENDER_USER_CONFIG`` / ``BLENDER_USER_SCRIPTS`` pointing at a
fresh profile, no ``PYTHONPATH``, no ``ESGS_PYTHON``, the current folder outside the
checkout). ``-S`` and appending ``SITE_PACKAGES`` (the bpy module's, without running its
``.pth`` files) keep the checkout's editable install of ``esgs`` out of this process: the
add-on can only come from the zip.

It installs the zip with Blender's extension API, sets up the trainer from the preferences
with WHEELS as the *Wheel Folder* (offline), then drives the operators as the panel's
buttons do: Generate -> Render Dataset -> Compute Priors -> Train (tiny; it imports the
result) -> File > Import Gaussians -> Compare to Mesh. It prints one JSON line with what it
found and how long each step took; the test asserts on it. It never imports anything of
the checkout (it is run by path, as a script).
"""
from __future__ import annotations

import importlib.util
import json
import math
import os
import sys
import time
from pathlib import Path

ZIP, SITE_PACKAGES, WHEELS, WORK = (Path(arg) for arg in sys.argv[1:5])
sys.path.append(str(SITE_PACKAGES))

found: dict = {"timings_s": {}, "reports": {}}
_clock = [time.perf_counter()]


def lap(name: str) -> None:
    now = time.perf_counter()
    found["timings_s"][name] = round(now - _clock[0], 2)
    _clock[0] = now


# nothing named esgs is importable before the extension is installed
found["esgs_before_install"] = importlib.util.find_spec("esgs") is not None
found["sys_path"] = list(sys.path)

import bpy  # noqa: E402
import addon_utils  # noqa: E402

lap("import_bpy")
bpy.ops.wm.read_factory_settings(use_empty=True)
found["install"] = sorted(bpy.ops.extensions.package_install_files(
    filepath=str(ZIP), repo="user_default", enable_on_install=True))
lap("install")
ADDON = "bl_ext.user_default.esgs"
addon = sys.modules[ADDON]
found["addon_file"] = addon.__file__
found["addon_enabled"] = ADDON in bpy.context.preferences.addons
found["addon_loaded"] = list(addon_utils.check(ADDON))
found["plain_esgs_modules"] = sorted(m for m in sys.modules if m == "esgs" or m.startswith("esgs."))
preferences = sys.modules[f"{ADDON}.esgs_addon.preferences"]
from bl_ext.user_default.esgs.esgs_addon import training_job  # noqa: E402
from bl_ext.user_default.esgs.core.apps import jobs  # noqa: E402

# ---------------------------------------------------------------- Preferences > Set Up Trainer
found["trainer_before"] = list(preferences.trainer_choice())
prefs = bpy.context.preferences.addons[ADDON].preferences
prefs.torch_variant = "CPU"
prefs.wheel_dir = str(WHEELS)


def run(name: str, operator, **kwargs) -> None:
    """Run an operator, recording its result and the messages it reported."""
    try:
        result = sorted(operator(**kwargs))
    except RuntimeError as error:  # an ERROR report raises under the bpy module
        result = ["ERROR", str(error)]
    found["reports"][name] = result
    lap(name)


run("trainer_setup", bpy.ops.esgs.trainer_setup)
found["setup_check"] = list(preferences.SETUP["check"])
found["trainer_after"] = list(preferences.trainer_choice())
found["environment_dir"] = str(preferences.environment_dir())

# ---------------------------------------------------------------- Generate -> Render Dataset
esgs = bpy.context.scene.esgs
terrain = esgs.terrain
terrain.preset = "rocky_slope"
terrain.seed = 1
terrain.views = 4
terrain.width, terrain.height, terrain.samples = 64, 48, 1
terrain.points_per_view = 200
run("generate_terrain", bpy.ops.esgs.generate_terrain)
terrain.output_dir = str(WORK / "scene")
run("render_dataset", bpy.ops.esgs.render_dataset)
found["training_scene_dir"] = esgs.training.scene_dir

# ---------------------------------------------------------------- Compute Priors (NDN: the shipped weights)
esgs.priors.method = "ndn"
found["priors_poll"] = bpy.ops.esgs.compute_priors.poll()
run("compute_priors", bpy.ops.esgs.compute_priors)
found["priors_state"] = [esgs.priors.status, esgs.priors.error]

# ---------------------------------------------------------------- Train (tiny; imports the result)
training = esgs.training
training.prior_source = "ndn"
training.iterations = 30
training.run_dir = str(WORK / "run")
run("train", bpy.ops.esgs.train)
found["training_state"] = [training.status, training.error, training.step, training.total]
job = jobs.get_job(training_job.job_key(training.last_scene_dir)) if training.last_scene_dir else None
found["training_command"] = list(job.trainer) if job is not None else []
trained = bpy.context.view_layer.objects.active
found["trained_object"] = [trained.name, trained.type, len(trained.data.points)] if trained is not None \
    and trained.type == "POINTCLOUD" else None

# ---------------------------------------------------------------- File > Import Gaussians
run("import_gaussians", bpy.ops.esgs.import_gaussians, filepath=str(WORK / "run" / "point_cloud.ply"))
imported = bpy.context.view_layer.objects.active
found["imported_object"] = [imported.name, imported.type, len(imported.data.points)] if imported is not None \
    and imported.type == "POINTCLOUD" else None

# ---------------------------------------------------------------- Compare to Mesh
# the generated terrain (world space, as the rendered scene's ground truth), chosen in the
# panel, against the Gaussians Train imported, made active (they know their run, so recall
# counts the surface its cameras saw); the button passes no arguments
from bl_ext.user_default.esgs.esgs_addon.terrain_scene import PROP_ROLE  # noqa: E402

terrain_mesh = next((o for o in bpy.data.objects if o.get(PROP_ROLE) == "terrain"), None)
found["mesh"] = terrain_mesh.name if terrain_mesh is not None else None
esgs.gaussians.mesh = terrain_mesh
esgs.gaussians.report_path = str(WORK / "compare.json")
esgs.gaussians.surface_samples = 5000
esgs.gaussians.compare_opacity_min = 0.0  # 30 steps leave every Gaussian fainter than the default 0.5
if trained is not None:
    bpy.context.view_layer.objects.active = trained
    run("compare_to_mesh", bpy.ops.esgs.compare_to_mesh)
compare = WORK / "compare.json"
summary = json.loads(compare.read_text()) if compare.is_file() else {}
found["compare"] = {key: summary.get(key) for key in (
    "n_gaussians", "n_gaussians_filtered", "precision", "recall", "fscore", "threshold_m", "recall_scope", "cameras", "frame")}
stats = summary.get("gaussians_to_mesh") or {}
found["compare"]["distances"] = {key: stats.get(key) for key in ("mean", "median")}
found["compare"]["finite"] = bool(stats) and all(
    isinstance(stats.get(key), (int, float)) and math.isfinite(stats[key]) for key in ("mean", "median"))

# ---------------------------------------------------------------- what this process imported
found["engine_modules_outside_extension"] = sorted(
    name for name, module in list(sys.modules.items())
    if (name == "esgs" or name.startswith(("esgs.", ADDON)))
    and getattr(module, "__file__", None) and not str(module.__file__).startswith(str(Path(addon.__file__).parent)))
found["cwd"] = os.getcwd()
(WORK / "found.json").write_text(json.dumps(found, indent=1))
print(json.dumps(found))
