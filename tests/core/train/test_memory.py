"""The training process stays lean: no needless heavy imports, freed heap memory handed back."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from esgs.core.train.memory import release_free_memory, resident_mib

#: Packages a training run on a COLMAP scene must not load: each costs tens of MiB resident
#: (pycolmap ~56 MiB, measured in docs/training.md "Memory") and none is needed to train.
NOT_FOR_TRAINING = ("pycolmap", "trimesh", "lpips", "OpenEXR", "sklearn", "matplotlib", "torchvision", "rtree")


def _modules_after(code: str) -> set[str]:
    """Top-level modules loaded by a fresh interpreter after running ``code``."""
    script = textwrap.dedent(code) + textwrap.dedent("""
        import json, sys
        print(json.dumps(sorted({name.split(".")[0] for name in sys.modules})))
        """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return set(json.loads(done.stdout.strip().splitlines()[-1]))


def test_a_training_run_loads_no_unneeded_heavy_package(tiny_scene, tmp_path):
    loaded = _modules_after(f"""
        from esgs.core.cli import main
        code = main(["train", {str(tiny_scene)!r}, "--out", {str(tmp_path / "run")!r}, "--iterations", "3",
                     "--backend", "reference", "--threads", "1", "--checkpoint-every", "0", "--no-lpips",
                     "--quiet"])
        assert code == 0, code
        """)
    assert "torch" in loaded and "esgs" in loaded  # it did train
    assert not loaded & set(NOT_FOR_TRAINING), sorted(loaded & set(NOT_FOR_TRAINING))
    assert (tmp_path / "run" / "point_cloud.ply").is_file()


def test_the_command_line_parser_does_not_load_torch():
    loaded = _modules_after("""
        from esgs.core.cli import build_parser
        build_parser().parse_args(["train", "scene", "--out", "run"])
        """)
    assert not loaded & {"torch", "numba", "cv2", "scipy", *NOT_FOR_TRAINING}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="malloc_trim and /proc are Linux (glibc) only")
def test_release_free_memory_returns_freed_heap_pages():
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        pytest.skip("not glibc: release_free_memory is a no-op there")
    # 160 MiB in 64 KiB blocks (below glibc's mmap threshold, so they live in the heap), then
    # a small block above them, so freeing them leaves a hole that free() cannot give back
    blocks = [bytearray(64 * 1024) for _ in range(2560)]
    pin = bytearray(64 * 1024)
    before = resident_mib()
    del blocks
    kept = resident_mib()
    assert release_free_memory() is True
    after = resident_mib()
    assert before - kept < 40, "glibc returned the hole by itself: the test no longer shows anything"
    assert kept - after > 120, (before, kept, after)
    del pin
