"""esgs bench through a local Ray instance: tables from the runs, retries, restarts, shipped folders."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

ray = pytest.importorskip("ray")

from esgs.core.experiments.bench import METHODS, run_bench  # noqa: E402
from esgs.core.experiments.executor import RayExecutor, run_tasks  # noqa: E402
from esgs.core.experiments.runs import RunTask, run_task  # noqa: E402
from esgs.core.experiments.tables import COST_COLUMNS, QUALITY_COLUMNS  # noqa: E402

from .helpers import make_experiment_scene  # noqa: E402
from .test_bench import TRAIN, _flaky  # noqa: E402

pytestmark = pytest.mark.slow  # Ray's start-up and one fresh worker per run: ~60 s on 2 busy cores


@pytest.fixture(scope="module")
def executor():
    """One light local Ray instance for the module (no dashboard, 80 MiB object store)."""
    if ray.is_initialized():
        pytest.skip("a Ray instance from elsewhere is already running in this process")
    # Ray's workers inherit the environment, not pytest's sys.path: they must import the test
    # module of _flaky by the dotted name pytest gave it (its first part may be the checkout's folder)
    module = _flaky.__module__
    root = str(Path(sys.modules[module].__file__).resolve().parents[module.count(".")])
    saved = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [root, saved]))
    try:
        with RayExecutor(num_cpus=2, object_store_mib=80) as started:
            assert started.started_here
            yield started
    finally:
        if saved is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = saved
    assert not ray.is_initialized()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_experiment_scene(tmp_path_factory.mktemp("bench_ray") / "scene")


def test_ray_executor_retries_a_failed_task_once_and_reports_a_second_failure(tmp_path, executor):
    tasks = [{"name": "flaky", "marker": str(tmp_path / "a")},
             {"name": "broken", "marker": str(tmp_path / "b"), "always": True}]
    outcomes = run_tasks(tasks, _flaky, executor, retries=1)
    assert [(o.status, o.attempts) for o in outcomes] == [("done", 2), ("failed", 2)]
    assert outcomes[0].result == "flaky"
    assert "planned failure of broken" in outcomes[1].error


def _row(rows: list[dict], variant: str) -> dict:
    return next(row for row in rows if row["variant"] == variant)


def test_tiny_bench_through_ray_tables_equal_the_runs_summaries_and_a_restart_trains_nothing(tmp_path, scene,
                                                                                          executor):
    methods = [m for m in METHODS if m.key in ("3dgs", "esgs_depth_normal")]
    seen = []
    report = run_bench(tmp_path / "bench", "quick", executor=executor, scenes={"tiny": (scene, 0)}, methods=methods,
                       iterations=4, budget_minutes=[0.002, 0.003], budget_step_cap=5000, train=TRAIN,
                       on_outcome=lambda o: seen.append((o.task.name, o.status)))
    assert sorted(seen) == [("tiny/3dgs", "done"), ("tiny/3dgs@0.003min", "done"), ("tiny/3dgs@budget", "done"),
                            ("tiny/esgs_depth_normal", "done"), ("tiny/esgs_depth_normal@0.003min", "done"),
                            ("tiny/esgs_depth_normal@budget", "done")]
    assert report["failed"] == [] and report["executor"] == "RayExecutor"
    assert "budget" not in report and len(report["budgets"]) == 2
    root = tmp_path / "bench"
    for comparison, folder in ((report, "runs"), (report["budgets"][0], "runs_budget"),
                               (report["budgets"][1], "runs_budget_0.003min")):
        assert len(comparison["runs"]) == 2
        for method in methods:
            stored = json.loads((root / folder / "tiny" / method.key / "summary.json").read_text())
            assert (root / folder / "tiny" / method.key / "point_cloud.ply").is_file()
            for rows in (comparison["overall"], comparison["per_scene"]["tiny"]):
                row = _row(rows, method.label)
                assert row["seeds"] == [0]
                for key, _, _ in QUALITY_COLUMNS + COST_COLUMNS + (("steps", "", 0),):
                    if key == "lpips":  # switched off in TRAIN: no figure, and the table says so
                        assert stored[key] is None and row[key]["n"] == 0
                    else:
                        assert row[key]["n"] == 1 and row[key]["mean"] == pytest.approx(stored[key]), key
    for run in report["runs"]:
        assert run["steps"] == 4 and run["status"] == "completed" and run["max_minutes"] is None
    for budget, cap in zip(report["budgets"], (5000, 7500)):
        assert budget["step_cap"] == cap
        for run in budget["runs"]:
            # stopped by the clock, not the cap: every method trained for (just over) the same time
            assert run["status"] == "time_limit" and run["iterations"] == cap and 1 <= run["steps"] < cap
            assert run["train_s"] >= budget["budget_minutes"] * 60 and run["max_minutes"] == budget["budget_minutes"]
    markdown = (root / "benchmarks.md").read_text()
    assert "## At equal step count (4 steps): all scenes" in markdown
    assert "## At equal wall-clock budget (0.002 min): all scenes" in markdown
    assert "## At equal wall-clock budget (0.003 min): all scenes" in markdown
    assert "steps reached" in markdown and "| ESGS: depth + normal |" in markdown

    seen.clear()
    again = run_bench(root, "quick", executor=executor, scenes={"tiny": (scene, 0)}, methods=methods,
                      iterations=4, budget_minutes=[0.002, 0.003], budget_step_cap=5000, train=TRAIN,
                      on_outcome=lambda o: seen.append(o.status))
    assert seen == ["skipped"] * 6
    assert again["overall"] == json.loads(json.dumps(report["overall"]))
    assert again["budgets"] == json.loads(json.dumps(report["budgets"]))


def test_shipped_run_trains_in_a_scratch_folder_and_its_folder_comes_back(tmp_path, scene, executor):
    # ship_folders=True does on one machine what an --address cluster does for a node without
    # the driver's disk: the scene goes through the object store and the run folder comes back
    shipping = RayExecutor(ship_folders=True)
    assert not shipping.started_here  # joined the module's instance
    out = tmp_path / "runs" / "tiny" / "3dgs"
    task = RunTask(name="tiny/3dgs", scene=scene, out=out, config={**TRAIN, "iterations": 3, "seed": 0},
                   variant="3DGS", scene_name="tiny", mesh=scene / "mesh" / "ground_truth.ply")
    [outcome] = run_tasks([task], run_task, shipping)
    shipping.close()
    assert ray.is_initialized()  # closing a joined executor leaves the instance running
    assert outcome.status == "done", outcome.error
    stored = json.loads((out / "summary.json").read_text())
    assert stored == json.loads(json.dumps(outcome.result))
    assert stored["steps"] == 3 and stored["distance_mean"] > 0  # the mesh travelled with the scene
    assert (out / "point_cloud.ply").stat().st_size > 0 and (out / "metrics.json").is_file()
    assert not (out / "checkpoints").exists()  # left behind on the node
    assert task.finished()
