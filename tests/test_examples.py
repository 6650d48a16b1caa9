"""The example scripts' shared loader (examples/esgs_loader.py) and one example run end to end."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _loader():
    spec = importlib.util.spec_from_file_location("esgs_loader_under_test", EXAMPLES / "esgs_loader.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_script_arguments_are_those_after_the_script_or_after_the_double_dash():
    loader = _loader()
    assert loader.script_arguments(["examples/x.py", "--out", "a"]) == ["--out", "a"]
    blender = ["/opt/blender/blender", "-b", "--python", "examples/x.py", "--", "--out", "a"]
    assert loader.script_arguments(blender) == ["--out", "a"]
    assert loader.script_arguments(["/opt/blender/blender", "-b", "--python", "examples/x.py"]) == []


def test_every_example_uses_the_shared_loader_and_defines_no_copy_of_it():
    scripts = [p for p in EXAMPLES.glob("*.py") if p.name != "esgs_loader.py"]
    assert len(scripts) >= 4
    for script in scripts:
        text = script.read_text()
        assert "from esgs_loader import" in text, script.name
        assert "def load_esgs" not in text and "def script_arguments" not in text, script.name


def test_a_plain_checkout_is_loaded_as_the_package_when_esgs_is_not_installed():
    # sys.modules["esgs"] = None makes `import esgs` fail as on a clone without the editable install
    code = (f"import sys; sys.modules['esgs'] = None; sys.path.insert(0, {str(EXAMPLES)!r})\n"
            "import esgs_loader\n"
            "esgs = esgs_loader.load_esgs()\n"
            "errors = esgs_loader.esgs_module(esgs, 'core.errors')\n"
            "print(esgs.__name__, esgs.__file__, errors.ESGSError.__module__)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    name, path, module = result.stdout.split()
    assert name == "esgs" and Path(path) == EXAMPLES.parent / "__init__.py" and module == "esgs.core.errors"


def test_terrain_preview_writes_its_overview_picture(tmp_path):
    out = tmp_path / "preview.png"
    command = [sys.executable, str(EXAMPLES / "terrain_preview.py"), "--preset", "dune_field", "--seed", "3",
               "--out", str(out)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "dune_field seed 3" in result.stdout
    from esgs.core.formats.imageio import read_image

    image = read_image(out)
    assert image.ndim == 3 and image.shape[2] == 3 and image.std() > 5  # a shaded relief, not a blank


@pytest.mark.parametrize("script", ["make_mars_scene.py", "import_colmap.py", "train_import_compare.py"])
def test_bpy_examples_start_and_describe_their_options(script):
    pytest.importorskip("bpy")
    result = subprocess.run([sys.executable, str(EXAMPLES / script), "--help"], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr
    assert "--out" in result.stdout or "--output" in result.stdout
