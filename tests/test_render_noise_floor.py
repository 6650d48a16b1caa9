"""benchmarks/render_noise_floor.py: a reused second render must hold the noise seed asked for."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from esgs.core.formats.scene_dir import SceneDir

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "render_noise_floor.py"


def _script():
    spec = importlib.util.spec_from_file_location("render_noise_floor", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_reused_render_must_record_the_noise_seed_asked_for(tmp_path):
    script = _script()
    out = tmp_path / "second"
    out.mkdir()
    provenance = SceneDir(out).provenance
    provenance.write_text(json.dumps({"seed": 4}))
    with pytest.raises(SystemExit, match="noise seed is not recorded .*pass another --out to render afresh$"):
        script.check_reused_render(out, 7)  # rendered before the seed was recorded
    script._record_noise_seed(out, 7)
    assert json.loads(provenance.read_text()) == {"seed": 4, "cycles_noise_seed": 7}
    script.check_reused_render(out, 7)
    with pytest.raises(SystemExit, match="--noise-seed 7 to reuse it"):
        script.check_reused_render(out, 8)
