"""Our CPU trainer against OpenSplat's CPU trainer, side by side on one scene (prints figures; not a test).

Usage::

    python benchmarks/bench_vs_opensplat.py --opensplat /path/to/opensplat \\
        [--scene SCENE] [--work DIR] [--iterations 1000] [--threads 1] [--sequential] [--lpips]

OpenSplat is not on any package registry and is never part of this repository: build it
from its public source (CPU mode, against the PyPI torch wheel's libtorch) outside the
tree; docs/training.md ("Against OpenSplat") gives the commands. Without the binary the
script prints why and exits 0.

What it does:

- SCENE (a COLMAP folder; made with ``esgs scene --preset cratered_plain --seed 0 --views
  30 --resolution 480x270 --samples 16`` when the folder does not exist) is split as our
  trainer splits it (sorted by name, every 8th image held out). OpenSplat trains on
  everything it is given, so it gets a copy of the scene holding only the training images
  (``images.bin`` rewritten; ``cameras.bin`` and ``points3D.bin`` copied byte for byte, so
  both start from the same SfM points).
- Both trainers run as child processes, by default at the same time (each sees the same
  machine load), each with ``--threads`` CPU threads (ours: ``--threads``; OpenSplat:
  ``OMP_NUM_THREADS``/``MKL_NUM_THREADS``, which bound libtorch's intra-op pool; its CPU
  rasterizer is single-threaded), at the same resolution (OpenSplat with
  ``--num-downscales 0``, so it never trains on smaller images) and for the same number of
  steps. OpenSplat's step-based settings are scaled to the run length the way ours are
  (``iterations / 30000``: densification start and interval, opacity-reset interval, SH
  degree interval, screen-size split limit) unless ``--opensplat-schedule default``.
- Step times: ours from ``events.jsonl`` (``--progress-every 1``: one timestamped event per
  step, with the Gaussian count); OpenSplat's from the time its per-step ``Step k:`` lines
  arrive, with the count followed through its "new count"/"remaining" lines.
- Peak resident memory of each child (``VmHWM`` sampled from /proc while it runs; ``wait4``'s
  ``ru_maxrss`` would include this benchmark's own size, inherited across the fork) and CPU
  time (user + system, setup included, from ``wait4``); CPU seconds per step depend less on
  the machine's load than wall-clock ones.
  Each trainer's memory is also given above its floor, the peak of its runtime doing nothing
  (ours: ``python -c "import torch"``; OpenSplat: ``opensplat --version``, libtorch loaded).
- Quality: both output PLYs are loaded with our PLY reader and rendered with our renderer
  on the same held-out views, each over what it was trained with (ours: its sky model,
  ``RUN/sky.json``, or black with ``--sky none`` / ``--vanilla``; OpenSplat's the nerfstudio
  colour it composites onto), and measured with our PSNR/SSIM (and LPIPS with ``--lpips``
  when its weights are cached). ``--ours-args`` passes further flags to ``esgs train``
  (``--ours-args=--vanilla`` for plain 3DGS); ``--json`` writes the figures.
- Cost model per trainer: least-squares fit of the median step time of each 10-step
  window against the window's mean Gaussian count, ``seconds = fixed + per_gaussian * N``;
  the ratio ours/OpenSplat is given at the Gaussian counts both runs went through.

The machine's load average is printed at the start and the end: on a shared machine the
figures are only comparable at similar load.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from esgs.core.formats.scene_dir import SceneDir
from esgs.core.formats.run_dir import RunDir

#: OpenSplat composites its renders onto this colour (nerfstudio's default, fixed in its Model).
OPENSPLAT_BACKGROUND = (0.6130, 0.0101, 0.3984)
#: Steps in one window of the cost-model fit.
FIT_WINDOW = 10
#: Steps averaged for the "early" and "late" seconds per step (the first steps are skipped:
#: they include one-off costs such as Numba compilation and the first allocations).
SPEED_SPAN = 50
SKIP_FIRST = 5

_STEP_LINE = re.compile(r"^Step (\d+): ")
_COUNT_LINE = re.compile(r"(?:new count|remaining) (\d+)")
_READ_POINTS_LINE = re.compile(r"^Reading (\d+) points")


@dataclass
class ChildRun:
    """One trainer's run: its per-step timeline and what it used."""

    name: str
    command: list[str]
    log: Path
    ply: Path
    steps: list[int] = field(default_factory=list)  # step numbers, in order
    times: list[float] = field(default_factory=list)  # wall-clock time (s) at the end of each step
    counts: list[int] = field(default_factory=list)  # Gaussians during each step
    peak_rss_mib: float = float("nan")
    floor_rss_mib: float = float("nan")  # the same runtime doing nothing (see floor_rss_mib())
    cpu_s: float = float("nan")  # user + system CPU time of the whole process (setup included)
    cpu_times: list[float] = field(default_factory=list)  # process CPU seconds at the end of each step
    wall_s: float = float("nan")
    returncode: Optional[int] = None
    metrics: dict = field(default_factory=dict)

    def step_seconds(self, cpu: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(step numbers [S-1], seconds of each step [S-1], Gaussians [S-1]) from consecutive end times.

        ``cpu``: CPU seconds of the process instead of wall-clock seconds.
        """
        times = np.asarray(self.cpu_times if cpu else self.times, dtype=np.float64)
        return np.asarray(self.steps[1:]), np.diff(times), np.asarray(self.counts[1:], dtype=np.float64)


# --- scene preparation -----------------------------------------------------------------------

def make_scene(scene: Path) -> None:
    """Render the benchmark scene with our generator (needs the bpy module; a few minutes)."""
    command = [sys.executable, "-m", "esgs.core", "scene", "--preset", "cratered_plain", "--seed", "0",
               "--views", "30", "--resolution", "480x270", "--samples", "16", "--out", str(scene)]
    print("making the scene:", " ".join(command), flush=True)
    subprocess.run(command, check=True)


def _write_images_bin(path: Path, images: list) -> None:
    """COLMAP ``images.bin`` with the given images and no 2D points (all OpenSplat reads)."""
    with open(path, "wb") as handle:
        handle.write(struct.pack("<Q", len(images)))
        for image in images:
            handle.write(struct.pack("<I", image.image_id))
            handle.write(struct.pack("<4d", *[float(v) for v in image.quat_wxyz]))
            handle.write(struct.pack("<3d", *[float(v) for v in image.translation]))
            handle.write(struct.pack("<I", image.camera_id))
            handle.write(image.name.encode("utf-8") + b"\0")
            handle.write(struct.pack("<Q", 0))


def training_only_scene(scene: Path, out: Path, test_every: int) -> list[str]:
    """A copy of ``scene`` for OpenSplat holding only our training images; returns the held-out names.

    Images are symbolic links; ``cameras.bin`` and ``points3D.bin`` are copied unchanged, so the
    initial points are the ones our trainer starts from.
    """
    from esgs.core.colmap.io import find_model_dir, read_model
    from esgs.core.train.dataset import split_indices

    model = read_model(scene)
    images = model.sorted_images()
    train_idx, test_idx = split_indices(len(images), test_every)
    model_dir, _ = find_model_dir(scene)
    if not (model_dir / "cameras.bin").is_file() or not (model_dir / "points3D.bin").is_file():
        raise SystemExit(f"{model_dir}: OpenSplat reads binary COLMAP models (cameras.bin, points3D.bin)")
    if out.exists():
        shutil.rmtree(out)
    folder = SceneDir(out)
    folder.images.mkdir(parents=True)
    sparse = folder.model
    sparse.mkdir(parents=True)
    shutil.copyfile(model_dir / "cameras.bin", sparse / "cameras.bin")
    shutil.copyfile(model_dir / "points3D.bin", sparse / "points3D.bin")
    train_images = [images[i] for i in train_idx]
    _write_images_bin(sparse / "images.bin", train_images)
    for image in train_images:
        folder.image(image.name).symlink_to(SceneDir(scene).image(image.name).resolve())
    return [images[i].name for i in test_idx]


# --- children --------------------------------------------------------------------------------

def _thread_environment(threads: int) -> dict:
    env = dict(os.environ)
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
        env[name] = str(threads)
    return env


def _opensplat_schedule(iterations: int, scaled: bool) -> list[str]:
    """OpenSplat flags for the run length: its defaults scaled by iterations / 30000 as ours are."""
    if not scaled:
        return []
    from esgs.core.train import TrainConfig

    ours = TrainConfig(iterations=iterations).schedule()
    refine_every = ours.densify_every
    return ["--warmup-length", str(ours.densify_from), "--refine-every", str(refine_every),
            # OpenSplat counts its reset interval in refinements, not steps
            "--reset-alpha-every", str(max(1, round(ours.opacity_reset_every / refine_every))),
            "--sh-degree-interval", str(ours.sh_increase_every),
            "--stop-screen-size-at", str(max(1, round(4000 * iterations / 30000)))]


def _wait(process: subprocess.Popen, run: ChildRun, started: float) -> None:
    """Reap ``process`` with wait4: exit code, wall and CPU time, and a first peak RSS (``ru_maxrss``,
    replaced by the sampled ``VmHWM`` in :func:`_cpu_at_steps`: see :func:`_process_peak_kib`)."""
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    run.returncode = process.returncode
    run.wall_s = time.monotonic() - started
    run.peak_rss_mib = usage.ru_maxrss / 1024.0
    run.cpu_s = usage.ru_utime + usage.ru_stime


#: Runs ``argv[1:]`` as its own child and prints that child's peak RSS (KiB) and exit code. A
#: process forked from this benchmark inherits its ~400 MiB (torch, NumPy) in ``ru_maxrss``, which
#: Linux carries over an exec: the peak of a small command would read as the benchmark's own size.
#: Forked from this small launcher (``python -S``, no site packages), it starts from a few MiB.
_PEAK_LAUNCHER = (
    "import os, sys\n"
    "pid = os.fork()\n"
    "if pid == 0:\n"
    "    null = os.open(os.devnull, os.O_RDWR)\n"
    "    os.dup2(null, 1); os.dup2(null, 2)\n"
    "    os.execvp(sys.argv[1], sys.argv[1:])\n"
    "_, status, usage = os.wait4(pid, 0)\n"
    "print(usage.ru_maxrss, os.waitstatus_to_exitcode(status))\n")


def floor_rss_mib(command: list[str], env: dict) -> float:
    """Peak resident memory (MiB) of ``command`` run to its end: a trainer's floor, what its
    runtime costs before any training (ours: the interpreter plus ``import torch``; OpenSplat:
    its binary with libtorch loaded, printing its version). Measured through
    :data:`_PEAK_LAUNCHER`, so the benchmark's own size does not leak into it."""
    done = subprocess.run([sys.executable, "-S", "-c", _PEAK_LAUNCHER, *command], capture_output=True, text=True,
                          env=env)
    try:
        peak_kib, code = (int(value) for value in done.stdout.split())
    except ValueError:
        raise SystemExit(f"the floor measurement {' '.join(command)!r} printed nothing usable: {done.stderr.strip()}")
    if code != 0:
        raise SystemExit(f"the floor measurement {' '.join(command)!r} failed (exit {code})")
    return peak_kib / 1024.0


def _process_cpu_s(pid: int) -> Optional[float]:
    """User + system CPU seconds of a running (or not yet reaped) process, from /proc."""
    try:
        with open(f"/proc/{pid}/stat") as handle:
            fields = handle.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _process_peak_kib(pid: int) -> Optional[int]:
    """Peak resident memory (KiB) of a running process since its exec (``VmHWM``), from /proc.

    Unlike ``ru_maxrss`` from ``wait4``, which keeps the peak of the process forked from this
    benchmark before its exec (the benchmark's own ~400 MiB of torch and NumPy), this is the
    trainer's own memory."""
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def _sample_cpu(pids: dict[int, list], stop: threading.Event, interval_s: float = 0.05) -> None:
    """Append (wall time, CPU seconds, peak KiB) of each process to ``pids[pid]`` until ``stop`` is set."""
    while not stop.is_set():
        for pid, samples in pids.items():
            value = _process_cpu_s(pid)
            peak = _process_peak_kib(pid)
            if value is not None and peak is not None:
                samples.append((time.time(), value, peak))
        stop.wait(interval_s)


def _cpu_at_steps(run: ChildRun, samples: list) -> None:
    """CPU seconds at each step's end, interpolated between the /proc samples (10 ms clock ticks),
    and the process's peak memory (its last ``VmHWM`` sample: the peak never falls)."""
    if samples:
        run.peak_rss_mib = max(sample[2] for sample in samples) / 1024.0
    if len(samples) >= 2:
        wall, cpu, _ = np.asarray(samples, dtype=np.float64).T
        run.cpu_times = [float(v) for v in np.interp(run.times, wall, cpu)]


def _follow_opensplat(process: subprocess.Popen, run: ChildRun, initial: list[int]) -> None:
    """Timestamp OpenSplat's per-step lines as they arrive; keep its Gaussian count."""
    count = None
    with open(run.log, "w") as log:
        for line in process.stdout:  # type: ignore[union-attr]
            now = time.time()
            log.write(line)
            match = _READ_POINTS_LINE.match(line)
            if match and count is None:
                count = int(match.group(1))
                initial.append(count)
            match = _COUNT_LINE.search(line)
            if match:
                count = int(match.group(1))  # takes effect from the next step on
            match = _STEP_LINE.match(line)
            if match:
                run.steps.append(int(match.group(1)))
                run.times.append(now)
                run.counts.append(count if count is not None else 0)


def _read_our_events(run: ChildRun, events: Path) -> None:
    previous = None
    for line in events.read_text().splitlines():
        event = json.loads(line)
        if event.get("stage") == "train" and event.get("kind") == "progress":
            count = int(event["metrics"]["n_gaussians"])  # after the step's densification
            run.steps.append(int(event["step"]))
            run.times.append(float(event["time"]))
            run.counts.append(count if previous is None else previous)  # the count the step rendered
            previous = count


def run_trainers(args: argparse.Namespace, scene: Path, opensplat_scene: Path, work: Path) -> tuple[ChildRun, ChildRun]:
    ours_dir = work / "ours"
    if ours_dir.exists():
        shutil.rmtree(ours_dir)
    ours = ChildRun(
        name="esgs (ours)",
        command=[sys.executable, "-m", "esgs.core", "train", str(scene), "--out", str(ours_dir),
                 "--iterations", str(args.iterations), "--width", str(args.width), "--threads", str(args.threads),
                 "--seed", str(args.seed), "--backend", "cpu", "--checkpoint-every", "0", "--progress-every", "1",
                 "--no-evaluate", "--quiet", *args.ours_args.split()],
        log=work / "ours.log", ply=RunDir(ours_dir).point_cloud)
    opensplat_dir = work / "opensplat"
    opensplat_dir.mkdir(parents=True, exist_ok=True)
    theirs = ChildRun(
        name="OpenSplat",
        command=[str(args.opensplat), str(opensplat_scene), "-o", str(opensplat_dir / "splat.ply"),
                 "-n", str(args.iterations), "--cpu", "--keep-crs", "--num-downscales", "0",
                 *_opensplat_schedule(args.iterations, args.opensplat_schedule == "scaled")],
        log=work / "opensplat.log", ply=opensplat_dir / "splat.ply")
    env = _thread_environment(args.threads)
    ours.floor_rss_mib = floor_rss_mib([sys.executable, "-c", "import torch"], env)
    theirs.floor_rss_mib = floor_rss_mib([str(args.opensplat), "--version"], env)
    print(f"floors: python + import torch {ours.floor_rss_mib:.0f} MiB, OpenSplat --version "
          f"{theirs.floor_rss_mib:.0f} MiB", flush=True)
    initial: list[int] = []

    def start_ours() -> tuple[subprocess.Popen, float]:
        print("ours:     ", " ".join(ours.command), flush=True)
        handle = open(ours.log, "w")
        return subprocess.Popen(ours.command, stdout=handle, stderr=subprocess.STDOUT, env=env), time.monotonic()

    def start_theirs() -> tuple[subprocess.Popen, float, threading.Thread]:
        print("OpenSplat:", " ".join(theirs.command), f"(OMP_NUM_THREADS={args.threads})", flush=True)
        process = subprocess.Popen(theirs.command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env,
                                   text=True, bufsize=1)
        reader = threading.Thread(target=_follow_opensplat, args=(process, theirs, initial), daemon=True)
        reader.start()
        return process, time.monotonic(), reader

    samples: dict[int, list] = {}
    stop = threading.Event()
    sampler = threading.Thread(target=_sample_cpu, args=(samples, stop), daemon=True)
    if args.sequential:
        process, started = start_ours()
        samples[process.pid] = our_samples = []
        sampler.start()
        _wait(process, ours, started)
        process, started, reader = start_theirs()
        samples[process.pid] = their_samples = []
        _wait(process, theirs, started)
        reader.join()
    else:
        our_process, our_start = start_ours()
        their_process, their_start, reader = start_theirs()
        our_samples, their_samples = [], []
        samples.update({our_process.pid: our_samples, their_process.pid: their_samples})
        sampler.start()
        # one waiter per child, so each one's wall time ends when it does
        waiters = [threading.Thread(target=_wait, args=(our_process, ours, our_start)),
                   threading.Thread(target=_wait, args=(their_process, theirs, their_start))]
        for waiter in waiters:
            waiter.start()
        for waiter in waiters:
            waiter.join()
        reader.join()
    if ours.returncode != 0:
        raise SystemExit(f"our trainer failed (exit {ours.returncode}); see {ours.log}")
    if theirs.returncode != 0:
        raise SystemExit(f"OpenSplat failed (exit {theirs.returncode}); see {theirs.log}")
    stop.set()
    sampler.join()
    _read_our_events(ours, RunDir(ours_dir).events)
    _cpu_at_steps(ours, our_samples)
    _cpu_at_steps(theirs, their_samples)
    return ours, theirs


# --- analysis --------------------------------------------------------------------------------

def _kept(run: ChildRun, until: float, cpu: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(seconds, Gaussians) of the steps after the first SKIP_FIRST that ended by wall-clock time ``until``."""
    steps, seconds, counts = run.step_seconds(cpu)
    keep = (steps > SKIP_FIRST) & (np.asarray(run.times[1:]) <= until)
    return seconds[keep], counts[keep]


def cost_model(run: ChildRun, until: float = float("inf"), cpu: bool = False) -> tuple[float, float, float]:
    """(fixed s, per-Gaussian s, R^2) of the median step time per window against the Gaussian count.

    NaN when there are fewer than 3 windows or the count changed by less than 10 % (no slope to fit).
    """
    seconds, counts = _kept(run, until, cpu)
    windows = len(seconds) // FIT_WINDOW
    if windows < 3 or (counts.max() - counts.min()) < 0.1 * counts.max():
        return float("nan"), float("nan"), float("nan")
    medians = np.array([np.median(seconds[i * FIT_WINDOW:(i + 1) * FIT_WINDOW]) for i in range(windows)])
    means = np.array([np.mean(counts[i * FIT_WINDOW:(i + 1) * FIT_WINDOW]) for i in range(windows)])
    design = np.stack([np.ones_like(means), means], axis=1)
    (fixed, per_gaussian), *_ = np.linalg.lstsq(design, medians, rcond=None)
    residual = medians - design @ np.array([fixed, per_gaussian])
    total = float(((medians - medians.mean()) ** 2).sum())
    r2 = 1.0 - float((residual ** 2).sum()) / total if total > 0 else float("nan")
    return float(fixed), float(per_gaussian), r2


def early_late(run: ChildRun, until: float = float("inf"), cpu: bool = False) -> tuple[float, float, float]:
    """Mean seconds per step: first SPEED_SPAN steps, last SPEED_SPAN steps, all (steps ending by ``until``)."""
    seconds, _ = _kept(run, until, cpu)
    return float(np.mean(seconds[:SPEED_SPAN])), float(np.mean(seconds[-SPEED_SPAN:])), float(np.mean(seconds))


def evaluate(run: ChildRun, scene: Path, width: int, background: tuple[float, float, float], threads: int,
             use_lpips: bool, renders: Path) -> dict:
    """Our PSNR/SSIM(/LPIPS) of ``run.ply`` on the scene's held-out views, rendered by our CPU rasterizer
    (over the sky model saved beside the PLY, if any)."""
    import torch

    from esgs.core.formats.ply import read_gaussians_ply
    from esgs.core.train.dataset import load_scene_data
    from esgs.core.train.evaluate import evaluate_model
    from esgs.core.train.gaussians import GaussianModel

    torch.set_num_threads(threads)
    data = load_scene_data(scene, width=width, test_every=8, mask_source="none")
    model = GaussianModel.from_ply(read_gaussians_ply(run.ply))
    sky = None
    sky_file = run.ply.parent / "sky.json"
    if sky_file.is_file():
        from esgs.core.train.sky import load_sky

        sky = load_sky(sky_file)
    return evaluate_model(model, data, backend="cpu", background=torch.tensor(background, dtype=torch.float32),
                          sh_degree=model.max_sh_degree, renders_dir=renders, use_lpips=use_lpips,
                          num_threads=threads, sky=sky)


def _ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}" if b and np.isfinite(a) and np.isfinite(b) else "n/a"


def _fmt(value) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return f"{'n/a':>12}"
    if isinstance(value, int) or abs(value) >= 100:
        return f"{value:12.1f}" if isinstance(value, float) else f"{value:12d}"
    return f"{value:12.4f}"


def _speed_rows(run: ChildRun, until: float, cpu: bool = False) -> dict:
    if cpu and len(run.cpu_times) != len(run.times):
        return {key: float("nan") for key in ("s/step early", "s/step late", "s/step mean", "fit fixed s",
                                               "fit us/Gaussian", "fit R^2")}
    early, late, mean = early_late(run, until, cpu)
    fixed, per_gaussian, r2 = cost_model(run, until, cpu)
    return {"s/step early": early, "s/step late": late, "s/step mean": mean, "fit fixed s": fixed,
            "fit us/Gaussian": per_gaussian * 1e6, "fit R^2": r2}


def _print_table(title: str, rows: list[dict]) -> None:
    print(f"\n{title}")
    print(f"{'':18} {'ours':>12} {'OpenSplat':>12} {'ours/OS':>8}")
    for key in rows[0]:
        a, b = rows[0][key], rows[1][key]
        ratio = _ratio(float(a), float(b)) if a is not None and b is not None and key != "fit R^2" else ""
        print(f"{key:18} {_fmt(a)} {_fmt(b)} {ratio:>8}")


def _equal_count_table(ours: ChildRun, theirs: ChildRun, until: float, bins: int = 6, cpu: bool = False) -> None:
    """Median measured s/step of both trainers in Gaussian-count bins both runs went through."""
    a_seconds, a_counts = _kept(ours, until, cpu)
    b_seconds, b_counts = _kept(theirs, until, cpu)
    low, high = max(a_counts.min(), b_counts.min()), min(a_counts.max(), b_counts.max())
    what = "CPU s/step, whole runs" if cpu else "s/step, while both ran"
    print(f"\nmeasured {what}, at equal Gaussian count (median of the steps in each bin):")
    if high < low:
        print("  the two runs never had the same Gaussian count; see the fits")
        return
    print(f"{'Gaussians':>19} {'ours':>8} {'n':>4} {'OpenSplat':>10} {'n':>4} {'ours/OS':>8}")
    edges = np.linspace(low, high, bins + 1) if high > low else np.array([low, high])
    for lo, hi in zip(edges[:-1], edges[1:]):
        a = a_seconds[(a_counts >= lo) & (a_counts <= hi)]
        b = b_seconds[(b_counts >= lo) & (b_counts <= hi)]
        if len(a) >= 5 and len(b) >= 5:
            print(f"{int(lo):9d}-{int(hi):<9d} {np.median(a):8.3f} {len(a):4d} {np.median(b):10.3f} {len(b):4d} "
                  f"{np.median(a) / np.median(b):8.2f}")


def report(ours: ChildRun, theirs: ChildRun, test_names: list[str]) -> None:
    """Print the side-by-side tables (whole runs, the time both ran, equal-count comparisons)."""
    overlap = min(ours.times[-1], theirs.times[-1])
    rows = []
    for run in (ours, theirs):
        row = _speed_rows(run, float("inf"))
        row.update({"Gaussians start": run.counts[0], "Gaussians max": max(run.counts),
                    "Gaussians final": run.counts[-1], "peak RSS MiB": run.peak_rss_mib,
                    "floor RSS MiB": run.floor_rss_mib, "RSS above floor MiB": run.peak_rss_mib - run.floor_rss_mib,
                    "wall s": run.wall_s,
                    "CPU s": run.cpu_s, "CPU s/step": run.cpu_s / max(run.steps[-1], 1),
                    "test PSNR": run.metrics.get("psnr"), "test SSIM": run.metrics.get("ssim"),
                    "test LPIPS": run.metrics.get("lpips")})
        rows.append(row)
    print(f"\nheld-out views ({len(test_names)}): {', '.join(test_names)}")
    _print_table("whole runs:", rows)
    both = [_speed_rows(run, overlap) for run in (ours, theirs)]
    steps_in_overlap = [int(np.sum(np.asarray(run.times) <= overlap)) for run in (ours, theirs)]
    _print_table(f"while both ran (steps ours {steps_in_overlap[0]}, OpenSplat {steps_in_overlap[1]}; "
                 "the same machine load for both):", both)
    _equal_count_table(ours, theirs, overlap)
    cpu_rows = [_speed_rows(run, float("inf"), cpu=True) for run in (ours, theirs)]
    _print_table("CPU seconds of each process per step, whole runs (less dependent on the load):", cpu_rows)
    if all(np.isfinite(row["s/step mean"]) for row in cpu_rows):
        _equal_count_table(ours, theirs, float("inf"), cpu=True)
    for title, rows_used in (("wall-clock fits while both ran", both), ("CPU-time fits", cpu_rows)):
        _modelled(title, rows_used, ours.counts + theirs.counts)
    print("\ntargets: ours/OS s/step at equal count <= 0.5, peak RSS above the floor <= 1 (issue 26), "
          "test PSNR/SSIM not lower")


def _modelled(title: str, rows: list[dict], counts: list[int]) -> None:
    fits = {name: (row["fit fixed s"], row["fit us/Gaussian"] * 1e-6) for name, row in zip(("ours", "os"), rows)}
    print(f"\nmodelled s/step at equal Gaussian count ({title}):")
    print(f"{'Gaussians':>10} {'ours':>8} {'OpenSplat':>10} {'ours/OS':>8}")
    for count in sorted({min(counts), int(np.median(counts)), max(counts), 50_000, 100_000}):
        a = fits["ours"][0] + fits["ours"][1] * count
        b = fits["os"][0] + fits["os"][1] * count
        print(f"{count:10d} {a:8.3f} {b:10.3f} {_ratio(a, b):>8}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--opensplat", type=Path, required=True, help="OpenSplat binary built for the CPU")
    parser.add_argument("--scene", type=Path, default=None,
                        help="COLMAP scene folder (made with esgs scene when it does not exist; default WORK/scene)")
    parser.add_argument("--work", type=Path, default=None, help="working folder (default: a temporary one)")
    parser.add_argument("--iterations", type=int, default=1000, help="training steps of each trainer")
    parser.add_argument("--threads", type=int, default=1, help="CPU threads of each trainer")
    parser.add_argument("--width", type=int, default=480, help="training and evaluation image width")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sequential", action="store_true", help="run the trainers one after the other")
    parser.add_argument("--opensplat-schedule", choices=("scaled", "default"), default="scaled",
                        help="scale OpenSplat's step-based settings to --iterations as ours are, or keep its defaults")
    parser.add_argument("--lpips", action="store_true", help="also LPIPS (needs cached weights)")
    parser.add_argument("--ours-args", default="", help="further flags for esgs train, e.g. --ours-args=--vanilla")
    parser.add_argument("--json", type=Path, default=None, help="write the figures (both runs) to this JSON file")
    args = parser.parse_args(argv)

    binary = args.opensplat
    if not (binary.is_file() and os.access(binary, os.X_OK)):
        print(f"SKIP: no OpenSplat binary at {binary}. OpenSplat is not on the package registries: build it "
              "from its public source in CPU mode outside this repository (docs/training.md, 'Against OpenSplat').")
        return 0
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_vs_opensplat_"))
    work.mkdir(parents=True, exist_ok=True)
    scene = args.scene or work / "scene"
    if not SceneDir(scene).has_model():
        make_scene(scene)
    scene = scene.resolve()
    version = subprocess.run([str(binary), "--version"], capture_output=True, text=True).stdout.strip()
    print(f"load average at start: {os.getloadavg()} on {os.cpu_count()} CPUs; OpenSplat {version}; "
          f"{args.iterations} steps each, {args.threads} thread(s) each, "
          f"{'one after the other' if args.sequential else 'at the same time'}", flush=True)
    test_names = training_only_scene(scene, work / "opensplat_scene", test_every=8)
    ours, theirs = run_trainers(args, scene, work / "opensplat_scene", work)
    print(f"load average after training: {os.getloadavg()}", flush=True)
    ours.metrics = evaluate(ours, scene, args.width, (0.0, 0.0, 0.0), args.threads, args.lpips, work / "renders_ours")
    theirs.metrics = evaluate(theirs, scene, args.width, OPENSPLAT_BACKGROUND, args.threads, args.lpips,
                              work / "renders_opensplat")
    report(ours, theirs, test_names)
    summary = {run.name: {"steps": run.steps, "times": run.times, "counts": run.counts, "peak_rss_mib": run.peak_rss_mib, "floor_rss_mib": run.floor_rss_mib, "cpu_s": run.cpu_s, "cpu_times": run.cpu_times,
                          "wall_s": run.wall_s, "metrics": run.metrics, "command": run.command} for run in (ours, theirs)}
    (work / "summary.json").write_text(json.dumps(summary))
    if args.json is not None:
        from esgs.core.io_utils import atomic_write_json

        atomic_write_json(args.json, {
            "command": "python benchmarks/bench_vs_opensplat.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "opensplat_version": version, "scene": str(scene), "held_out": test_names,
            "iterations": args.iterations, "threads": args.threads, "width": args.width,
            "runs": {run.name: {"command": run.command, "metrics": run.metrics, "wall_s": run.wall_s,
                                "cpu_s": run.cpu_s, "peak_rss_mib": run.peak_rss_mib,
                                "floor_rss_mib": run.floor_rss_mib,
                                "rss_above_floor_mib": run.peak_rss_mib - run.floor_rss_mib,
                                "max_gaussians": max(run.counts) if run.counts else None,
                                "final_gaussians": run.counts[-1] if run.counts else None}
                     for run in (ours, theirs)}})
    print(f"\nper-step timelines: {work / 'summary.json'}; load average at end: {os.getloadavg()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
