"""The OpenSplat comparison script's own helpers (the comparison itself needs the OpenSplat binary)."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import benchmark_script

from esgs.core.colmap.model import Image
from esgs.core.colmap.parse import read_images_binary



@pytest.fixture(scope="module")
def bench():
    with benchmark_script("bench_vs_opensplat") as module:
        yield module


def test_skips_with_a_message_when_the_binary_is_missing(bench, tmp_path, capsys):
    assert bench.main(["--opensplat", str(tmp_path / "no_such_opensplat"), "--work", str(tmp_path / "work")]) == 0
    out = capsys.readouterr().out
    assert out.startswith("SKIP:") and "no_such_opensplat" in out
    assert not (tmp_path / "work").exists()  # nothing was prepared


def test_images_bin_is_read_back_by_a_colmap_reader(bench, tmp_path):
    rng = np.random.default_rng(3)
    images = []
    for image_id, name in ((4, "view_001.png"), (9, "b c.png")):
        quat = rng.normal(size=4)
        images.append(Image(image_id=image_id, name=name, camera_id=2, quat_wxyz=quat / np.linalg.norm(quat),
                            translation=rng.normal(size=3), points2d=np.zeros((0, 2)),
                            point3d_ids=np.zeros(0, dtype=np.int64)))
    path = tmp_path / "images.bin"
    bench._write_images_bin(path, images)
    read = read_images_binary(path)
    assert sorted(read) == [4, 9]
    for image in images:
        back = read[image.image_id]
        assert back.name == image.name and back.camera_id == 2
        np.testing.assert_array_equal(back.quat_wxyz, image.quat_wxyz)
        np.testing.assert_array_equal(back.translation, image.translation)
        assert len(back.points2d) == 0


def _timeline(bench, fixed: float, per_gaussian: float, noise: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    counts = np.repeat(np.linspace(50_000, 150_000, 30).astype(int), 10)  # grows every 10 steps
    seconds = fixed + per_gaussian * counts + rng.normal(scale=noise, size=len(counts))
    times = np.concatenate([[0.0], np.cumsum(seconds)])
    return bench.ChildRun(name="x", command=[], log=Path("x"), ply=Path("x"), steps=list(range(len(times))),
                          times=list(times), counts=[int(counts[0])] + [int(c) for c in counts])


def test_cost_model_recovers_fixed_and_per_gaussian_cost(bench):
    run = _timeline(bench, fixed=0.075, per_gaussian=9e-6, noise=0.01)
    fixed, per_gaussian, r2 = bench.cost_model(run)
    assert fixed == pytest.approx(0.075, abs=0.02)
    assert per_gaussian == pytest.approx(9e-6, rel=0.05)
    assert r2 > 0.95
    # only the steps that ended before a time limit count
    half = run.times[len(run.times) // 2]
    seconds, counts = bench._kept(run, half)
    assert len(seconds) < len(run.times) // 2 and counts.max() < 110_000


def test_cost_model_refuses_a_flat_gaussian_count(bench):
    run = _timeline(bench, fixed=0.075, per_gaussian=9e-6, noise=0.01)
    run.counts = [60_000] * len(run.counts)
    assert np.isnan(bench.cost_model(run)[1])


def test_process_cpu_time_from_proc_follows_the_work_done(bench):
    import os
    import time

    before = bench._process_cpu_s(os.getpid())
    deadline = time.process_time() + 0.3
    while time.process_time() < deadline:  # 0.3 s of CPU work
        pass
    after = bench._process_cpu_s(os.getpid())
    assert after - before == pytest.approx(0.3, abs=0.1)
    assert bench._process_cpu_s(2**22 + 12345) is None  # no such process


def test_a_floor_is_the_peak_memory_of_the_command_and_grows_with_what_it_touches(bench):
    env = dict(os.environ)
    idle = bench.floor_rss_mib([sys.executable, "-c", "pass"], env)
    touched = bench.floor_rss_mib([sys.executable, "-c", "b = bytearray(300 * 2**20); b[::4096] = b'x' * len(b[::4096])"],
                                  env)
    assert 1.0 < idle < touched
    assert touched - idle > 250.0  # the 300 MiB it wrote count, to within what the interpreter shares
    with pytest.raises(SystemExit, match="failed"):
        bench.floor_rss_mib([sys.executable, "-c", "raise SystemExit(3)"], env)


def test_a_running_childs_peak_is_its_own_not_the_forking_benchmarks(bench):
    ballast = bytearray(200 * 2**20)  # this process grows by 200 MiB before it forks the child
    ballast[::4096] = b"x" * len(ballast[::4096])
    child = subprocess.Popen([sys.executable, "-S", "-c", "import time; time.sleep(0.6)"])
    samples: dict[int, list] = {child.pid: []}
    stop = threading.Event()
    sampler = threading.Thread(target=bench._sample_cpu, args=(samples, stop, 0.02))
    sampler.start()
    child.wait()
    stop.set()
    sampler.join()
    run = bench.ChildRun(name="child", command=[], log=Path("log"), ply=Path("ply"))
    run.times = [samples[child.pid][-1][0]]
    bench._cpu_at_steps(run, samples[child.pid])
    assert 1.0 < run.peak_rss_mib < 100.0  # a bare interpreter, not the ~200 MiB parent
    del ballast
