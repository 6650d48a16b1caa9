"""esgs bench through the local process pool: tiny runs, restart skips, retries and failures."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from esgs.core.errors import ConfigError
from esgs.core.experiments.bench import (METHODS, PRIOR_CHOICES, SUITES, UPPER_BOUND_KEY, bench_rows, budget_plan,
                                         ensure_priors, plan_bench, report_budgets, run_bench, select_methods)
from esgs.core.experiments.executor import LocalExecutor, make_executor, run_tasks
from esgs.core.experiments.runs import RunTask

from .helpers import make_experiment_scene

TRAIN = {"backend": "cpu", "threads": 1, "lpips": False, "densify_until": 0, "test_every": 3, "save_renders": False,
         "checkpoint_every": 0, "sh_degree": 1, "init_opacity": 0.7}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_experiment_scene(tmp_path_factory.mktemp("bench") / "scene")


def _flaky(task: dict) -> str:
    """Fails on the first call for a task (leaves a marker), succeeds on the second; 'always' always fails."""
    marker = Path(task["marker"])
    if task.get("always") or not marker.exists():
        marker.write_text("tried")
        raise RuntimeError(f"planned failure of {task['name']}")
    return task["name"]


def test_local_executor_retries_a_failed_task_once_and_reports_a_second_failure(tmp_path):
    tasks = [{"name": "flaky", "marker": str(tmp_path / "a")},
             {"name": "broken", "marker": str(tmp_path / "b"), "always": True}]
    with LocalExecutor(2) as executor:
        outcomes = run_tasks(tasks, _flaky, executor, retries=1)
    assert [(o.status, o.attempts) for o in outcomes] == [("done", 2), ("failed", 2)]
    assert outcomes[0].result == "flaky"
    assert "planned failure of broken" in outcomes[1].error


def test_ray_executor_needs_ray_or_says_so():
    try:
        import ray  # noqa: F401
    except ImportError:
        with pytest.raises(ConfigError, match="ray"):
            make_executor("auto", address="auto")
    assert isinstance(make_executor("auto"), LocalExecutor)


def test_suites_name_their_presets_and_the_plan_skips_methods_without_priors(tmp_path, scene):
    assert SUITES["quick"].presets == ("cratered_plain",) and SUITES["full"].seeds == (0, 1, 2)
    bare = tmp_path / "bare"
    (bare / "sparse").mkdir(parents=True)
    tasks, notes = plan_bench({"tiny": (scene, 0), "bare": (bare, 1)}, tmp_path / "out", iterations=5, priors="gt")
    # with gt priors the full-ESGS row on gt is the labelled upper bound: one row, not two
    assert len([t for t in tasks if t.scene_name == "tiny"]) == len(METHODS) - 1
    assert {t.variant for t in tasks if t.scene_name == "bare"} == {"3DGS", "3DGS + sky model (our defaults)",
                                                                   "Mip-Splatting", "DropoutGS", "PGSR", "Scaffold-GS",
                                                                   "3DGS + GPDFN"}
    assert len(notes) == 4 and all("bare" in note for note in notes)
    full = next(t for t in tasks if t.name == f"tiny/{UPPER_BOUND_KEY}")
    assert full.config["method"] == "esgs" and "upper bound" in full.variant
    assert full.config["method_config"]["priors"] == "gt" and full.config["method_config"]["gpdfn"] is True


def test_the_report_names_the_prior_source_and_labels_the_upper_bound():
    from esgs.core.experiments.bench import _priors_sentence

    assert "exact depth and normals." in _priors_sentence(None) and "upper bound" not in _priors_sentence(None)
    ndn = _priors_sentence({"source": "ndn", "weights": ["ndn_mars.pt"]})
    assert "NDN" in ndn and "ndn_mars.pt" in ndn and "upper bound" in ndn
    assert "sparse SfM depth" in _priors_sentence({"source": "sfm"})
    auto = _priors_sentence({"source": "auto", "sources": ["auto"], "weights": ["ndn_mars.pt"]})
    assert auto.startswith("Priors: the ESGS rows use the `auto` priors") and "ndn_mars.pt" in auto
    several = _priors_sentence({"source": "auto", "sources": ["auto", "labels", "ndn"]})
    assert "'ESGS (auto)', 'ESGS (labels)', 'ESGS (ndn)'" in several and "stereo labels" in several
    assert "ablation rows (ESGS: depth prior, normal prior, depth + normal) use auto" in several


def test_run_bench_makes_each_source_once_auto_last_and_plans_the_rows_on_all(tmp_path, scene, monkeypatch):
    from esgs.core.experiments import bench

    made, planned = [], {}

    def fake_plan(scenes, out, **kwargs):
        planned.update(kwargs)
        return [], []

    monkeypatch.setattr(bench, "ensure_priors", lambda folder, source: made.append((folder, source)))
    monkeypatch.setattr(bench, "plan_bench", fake_plan)
    report = run_bench(tmp_path / "bench", "quick", scenes={"tiny": (scene, 0)}, budget_minutes=0, iterations=4,
                       train=TRAIN, priors=["auto", "labels", "ndn", "gt"])
    # auto is fused from labels and ndn: made after them; gt comes only from the generator
    assert made == [(scene, "labels"), (scene, "ndn"), (scene, "auto")]
    assert planned["priors"] == ("auto", "labels", "ndn", "gt")
    assert report["priors"]["sources"] == ["auto", "labels", "ndn", "gt"] and report["priors"]["source"] == "auto"
    assert report["sparse_points"]["kind"] == "exact" and report["suite"]["sparse_points"] == "triangulated"
    with pytest.raises(ConfigError, match="sparse points"):
        run_bench(tmp_path / "bench", "quick", scenes={"tiny": (scene, 0)}, sparse_points="surface")


def test_prior_rows_use_the_chosen_source_and_only_the_labelled_upper_bound_row_uses_gt(tmp_path, scene):
    # the tiny scene has gt priors only: with the default (auto) the ESGS rows have nothing to read
    tasks, notes = plan_bench({"tiny": (scene, 0)}, tmp_path / "out", iterations=5)
    planned = {t.name.split("/")[1]: t for t in tasks}
    assert set(planned) == {"3dgs", "3dgs_sky", "mip_splatting", "dropout_gs", "pgsr", "scaffold_gs", "3dgs_gpdfn",
                            UPPER_BOUND_KEY}
    # the published baselines run vanilla; the sky-model row and ESGS keep the defaults
    for key in ("3dgs", "mip_splatting", "dropout_gs", "pgsr", "scaffold_gs"):
        assert planned[key].config["sky"] == "none" and planned[key].config["mask_source"] == "none"
    assert planned["pgsr"].config["method"] == "pgsr" and planned["scaffold_gs"].config["method"] == "scaffold-gs"
    for key in ("3dgs_sky", "3dgs_gpdfn", UPPER_BOUND_KEY):
        assert "sky" not in planned[key].config and "mask_source" not in planned[key].config
    assert planned[UPPER_BOUND_KEY].config["method_config"]["priors"] == "gt" and "upper bound" in planned[UPPER_BOUND_KEY].variant
    assert len(notes) == 4 and all("no auto" in note for note in notes)
    assert any(note.startswith("ESGS (auto) skipped on tiny") for note in notes)
    # stereo labels are a source the bench can compare (esgs labels --reconstruct makes them)
    _, notes = plan_bench({"tiny": (scene, 0)}, tmp_path / "out", iterations=5, priors="labels")
    assert len(notes) == 4 and all("no labels" in note for note in notes)
    with pytest.raises(ConfigError, match="unknown prior source 'mesh'"):
        plan_bench({"tiny": (scene, 0)}, tmp_path / "out", iterations=5, priors=["auto", "mesh"])
    with pytest.raises(ConfigError, match="no prior source"):
        plan_bench({"tiny": (scene, 0)}, tmp_path / "out", iterations=5, priors=[])


def _with_priors(scene, root, *sources):
    """A copy of ``scene`` whose gt maps also stand for ``sources`` (the plan only looks for the folders)."""
    import shutil

    copy = root / "scene"
    shutil.copytree(scene, copy)
    for source in sources:
        shutil.copytree(copy / "priors" / "gt", copy / "priors" / source)
    return copy


def test_the_default_rows_are_esgs_on_auto_priors_and_3dgs_plus_gpdfn(tmp_path, scene):
    from esgs.core.config import config_to_dict
    from esgs.core.methods import ESGSConfig, full_esgs

    copy = _with_priors(scene, tmp_path, "auto")
    tasks, notes = plan_bench({"tiny": (copy, 0)}, tmp_path / "out", iterations=5)
    planned = {t.name.split("/")[1]: t for t in tasks}
    assert notes == [] and "3dgs_gpdfn" in {m.key for m in METHODS}
    assert set(planned) == {"3dgs", "3dgs_sky", "mip_splatting", "dropout_gs", "pgsr", "scaffold_gs", "3dgs_gpdfn",
                            "esgs_depth", "esgs_normal", "esgs_depth_normal", "esgs_full_auto", UPPER_BOUND_KEY}
    # full ESGS on auto, the one definition (esgs.core.methods.full_esgs); the ablations read auto too
    full = planned["esgs_full_auto"]
    assert full.variant == "ESGS (auto)" and full.config["method"] == "esgs"
    assert full.config["method_config"] == config_to_dict(full_esgs("auto", scene=copy))
    assert all(planned[key].config["method_config"]["priors"] == "auto"
               for key in ("esgs_depth", "esgs_normal", "esgs_depth_normal"))
    # 3DGS + GPDFN: full ESGS with every prior dropped, GPDFN (K = 3) kept
    gpdfn = planned["3dgs_gpdfn"]
    settings = gpdfn.config["method_config"]
    assert gpdfn.variant == "3DGS + GPDFN" and gpdfn.config["method"] == "esgs"
    assert settings["priors"] == "" and settings["gpdfn"] is True and settings["fused_k"] == 3
    assert not (settings["depth"] or settings["normal"] or settings["consistency"]) and settings["sky_weight"] == 0
    assert ESGSConfig(**settings).enabled and not ESGSConfig(**settings).sky_loss_on
    assert settings["prior_points"] == 0  # nothing seeded without priors
    # it is the full method's GPDFN: every setting but the prior ones is full ESGS's
    prior_fields = {"priors", "depth", "normal", "consistency", "sky_weight", "depth_weight", "prior_points"}
    assert {k: v for k, v in settings.items() if k not in prior_fields} == \
        {k: v for k, v in full.config["method_config"].items() if k not in prior_fields}
    # it needs no priors: planned on a scene without any, whatever the source
    bare = tmp_path / "bare"
    (bare / "sparse").mkdir(parents=True)
    tasks, _ = plan_bench({"bare": (bare, 0)}, tmp_path / "out", iterations=5, priors="ndn")
    assert "bare/3dgs_gpdfn" in {t.name for t in tasks}
    assert next(t for t in tasks if t.name == "bare/3dgs_gpdfn").config["method_config"] == settings


def test_several_prior_sources_give_full_esgs_rows_side_by_side(tmp_path, scene):
    copy = _with_priors(scene, tmp_path, "auto", "labels", "ndn")
    tasks, notes = plan_bench({"tiny": (copy, 0)}, tmp_path / "out", iterations=5, priors=["auto", "labels", "ndn"])
    planned = {t.name.split("/")[1]: t for t in tasks}
    assert notes == []
    for source in ("auto", "labels", "ndn"):
        row = planned[f"esgs_full_{source}"]
        assert row.variant == f"ESGS ({source})" and row.config["method_config"]["priors"] == source
        assert row.out == tmp_path / "out" / "runs" / "tiny" / f"esgs_full_{source}"
    assert "esgs_full_gt" in planned and "upper bound" in planned["esgs_full_gt"].variant
    # the ablation rows use the first source
    assert {planned[key].config["method_config"]["priors"] for key in ("esgs_depth", "esgs_normal")} == {"auto"}
    # gt among the sources: its full-ESGS row is the upper bound's, trained once
    rows = [method for method, _ in bench_rows(METHODS, ["ndn", "gt", "ndn"])]
    assert [m.key for m in rows if m.key.startswith("esgs_full")] == ["esgs_full_ndn", UPPER_BOUND_KEY]


def test_the_bench_computes_missing_sfm_priors_and_plans_its_rows_on_them(tmp_path, scene):
    import shutil

    copy = tmp_path / "scene"
    shutil.copytree(scene, copy)
    folder = ensure_priors(copy, "sfm")
    assert folder == copy / "priors" / "sfm" and sorted(p.name for p in (folder / "depth").glob("*.exr"))
    assert ensure_priors(copy, "sfm") == folder  # present: reused, not recomputed
    tasks, notes = plan_bench({"tiny": (copy, 0)}, tmp_path / "out", iterations=5, priors="sfm")
    sources = {t.name.split("/")[1]: (t.config["method_config"] or {}).get("priors") for t in tasks}
    # sfm priors are depth only: the normal-prior rows are left out with a note, the depth row uses
    # sfm, and full ESGS (esgs.core.methods.full_esgs) trains depth + consistency + GPDFN on them
    assert sources["esgs_depth"] == "sfm" and sources[UPPER_BOUND_KEY] == "gt" and sources["esgs_full_sfm"] == "sfm"
    assert sources["3dgs_gpdfn"] == ""
    full = next(t for t in tasks if t.name == "tiny/esgs_full_sfm").config["method_config"]
    assert full["depth"] and full["consistency"] and not full["normal"] and full["gpdfn"]
    assert len(notes) == 2 and all("normal" in note and "no sfm" in note for note in notes)
    bare = tmp_path / "bare"
    (bare / "sparse").mkdir(parents=True)
    with pytest.raises(ConfigError, match="gt priors"):
        ensure_priors(bare, "gt")


def test_missing_labels_are_reconstructed_from_the_images_never_the_mesh(tmp_path, monkeypatch):
    from esgs.core.errors import ESGSError
    from esgs.core.experiments import bench

    calls = []

    def fake_run_job(job, config, progress=None, **kwargs):
        calls.append((job, config))
        if len(calls) == 1:  # the first try fails: the child's error is in the message
            raise ESGSError("stereo found no consistent depth")
        (tmp_path / "priors" / "labels" / "depth").mkdir(parents=True)
        (tmp_path / "priors" / "labels" / "depth" / "v.exr").write_bytes(b"")

    monkeypatch.setattr(bench, "run_job", fake_run_job)
    with pytest.raises(ESGSError, match="esgs labels --reconstruct failed: stereo found no consistent depth"):
        ensure_priors(tmp_path, "labels")
    assert ensure_priors(tmp_path, "labels") == tmp_path / "priors" / "labels"
    job, config = calls[-1]
    assert job == "labels" and config.scene == tmp_path and config.reconstruct and config.mesh is None
    assert ensure_priors(tmp_path, "labels") == tmp_path / "priors" / "labels" and len(calls) == 2  # reused


def test_a_run_saved_with_other_settings_is_stale_and_set_aside_whole(tmp_path, scene):
    from esgs.core.config import config_from_dict, config_to_dict
    from esgs.core.train.config import TrainConfig

    from esgs.core.methods import DropoutGSConfig, ESGSConfig, MipSplattingConfig

    def saved_config(task):
        """The config.json a run of ``task`` saved before methods were registered (the legacy
        "esgs" and "baselines" sections): such folders must keep comparing right."""
        legacy = {key: task.config[key] for key in ("esgs", "baselines")}
        values = {key: value for key, value in task.config.items() if key not in legacy}
        values = config_to_dict(config_from_dict(TrainConfig, {**values, "scene": str(scene), "out": str(task.out)}))
        del values["method"], values["method_config"]
        baselines = {"mip_splatting": False, **config_to_dict(MipSplattingConfig()), "dropout_gs": False,
                     **config_to_dict(DropoutGSConfig()), **legacy["baselines"]}
        esgs = config_to_dict(ESGSConfig(**legacy["esgs"]))
        return json.loads(json.dumps({**values, "esgs": esgs, "baselines": baselines}))

    out = tmp_path / "run"
    esgs = {"priors": "gt", "depth": True}
    task = RunTask(name="tiny/esgs_depth", scene=scene, out=out, config={**TRAIN, "iterations": 5, "seed": 0,
                                                                          "esgs": esgs, "baselines": {}})
    assert task.stale_settings() == [] and not task.finished()  # nothing saved yet
    saved = saved_config(task)
    out.mkdir()
    # settings that change only how it runs (threads) may differ
    (out / "config.json").write_text(json.dumps({**saved, "threads": 7}))
    (out / "summary.json").write_text("{}")
    assert task.stale_settings() == [] and task.finished()
    # a changed default inside the ESGS settings, a step count, and a run older than the
    # Gaussians' spatial order (split offsets pair up with other Gaussians: another sample)
    saved["esgs"]["depth_weight"] = 0.1
    saved["iterations"] = 6
    del saved["spatial_order"]
    (out / "config.json").write_text(json.dumps(saved))
    assert task.stale_settings() == ["iterations", "method_config", "spatial_order"] and not task.finished()
    moved = task.set_aside_if_stale()
    assert moved is not None and moved.name.startswith("run.stale-") and not out.exists()
    assert json.loads((moved / "config.json").read_text())["esgs"]["depth_weight"] == 0.1
    assert (moved / "summary.json").is_file() and task.set_aside_if_stale() is None
    # a 3DGS run does not depend on the settings of switched-off methods
    plain = RunTask(name="tiny/3dgs", scene=scene, out=tmp_path / "plain",
                    config={**TRAIN, "iterations": 5, "seed": 0, "esgs": {}, "baselines": {}})
    saved = saved_config(plain)
    saved["esgs"]["depth_weight"], saved["baselines"]["dropout_rate"] = 0.1, 0.5
    del saved["esgs"]["relative_alignment"]  # an ESGS setting newer than the run
    plain.out.mkdir()
    (plain.out / "config.json").write_text(json.dumps(saved))
    assert plain.stale_settings() == []
    saved["baselines"]["dropout_gs"] = True
    (plain.out / "config.json").write_text(json.dumps(saved))
    assert plain.stale_settings() == ["method", "method_config"]
    # a nested setting newer than the run (the sky loss) counts with its old value, off: such a
    # run is what a request with the loss off asks for, and stale for today's default (0.3, on)
    sky = RunTask(name="tiny/esgs_sky", scene=scene, out=tmp_path / "sky",
                  config={**TRAIN, "iterations": 5, "seed": 0, "esgs": {**esgs, "sky_weight": 0.0}, "baselines": {}})
    saved = saved_config(sky)
    del saved["esgs"]["sky_weight"]
    sky.out.mkdir()
    (sky.out / "config.json").write_text(json.dumps(saved))
    assert sky.stale_settings() == []
    sky.config["esgs"] = dict(esgs)  # the default weight
    assert sky.stale_settings() == ["method_config"]
    sky.config["esgs"] = {**esgs, "sky_weight": 0.5}
    assert sky.stale_settings() == ["method_config"]
    # with no prior source the sky loss cannot act, so a 3DGS run with a weight set is still 3DGS
    plain.config["esgs"] = {"sky_weight": 0.5}
    saved = saved_config(plain)
    del saved["esgs"]["sky_weight"]
    (plain.out / "config.json").write_text(json.dumps(saved))
    assert plain.stale_settings() == []



def test_settings_of_a_switched_off_esgs_part_do_not_make_a_run_stale(tmp_path, scene):
    """A depth-only run saved with another normal-prior form, GPDFN rate or consistency weight is
    the same run (those parts are off); a change to a part that is on, or to a switch, is not."""
    from esgs.core.config import config_to_dict
    from esgs.core.methods import train_config_from_dict

    def task_saved_with(request: dict, **saved_changes) -> RunTask:
        out = tmp_path / f"run{len(list(tmp_path.iterdir()))}"
        task = RunTask(name="tiny/esgs", scene=scene, out=out,
                       config={**TRAIN, "iterations": 5, "seed": 0, "method": "esgs", "method_config": request})
        saved = config_to_dict(train_config_from_dict({**task.config, "scene": str(scene), "out": str(out)},
                                                      saved=False))
        saved["method_config"].update(saved_changes)
        out.mkdir()
        (out / "config.json").write_text(json.dumps(saved))
        return task

    depth_only = {"priors": "gt", "depth": True}
    assert task_saved_with(depth_only).stale_settings() == []
    assert task_saved_with(depth_only, normal_render="composited", normal_weight=0.05, gpdfn_lr=0.1,
                           gpdfn_every=4, consistency_weight=1.0).stale_settings() == []
    assert task_saved_with(depth_only, depth_decay=0.5).stale_settings() == ["method_config"]
    assert task_saved_with(depth_only, normal=True).stale_settings() == ["method_config"]
    with_normal = {**depth_only, "normal": True}
    assert task_saved_with(with_normal, normal_render="composited").stale_settings() == ["method_config"]
    # GPDFN is on only with fused_k > 1: fused_k is a switch, its other settings count when it is on
    gpdfn = {**depth_only, "gpdfn": True}
    assert task_saved_with(gpdfn, fused_k=1).stale_settings() == ["method_config"]
    assert task_saved_with(gpdfn, gpdfn_lr=0.1).stale_settings() == ["method_config"]
    assert task_saved_with({**gpdfn, "fused_k": 1}, gpdfn_lr=0.1).stale_settings() == []

def test_budget_plan_gives_every_method_the_same_minutes_and_step_cap_in_its_own_folder(tmp_path, scene):
    tasks, _ = plan_bench({"tiny": (scene, 0)}, tmp_path / "out", iterations=300, budget_minutes=1.5, priors="gt")
    steps = {t.variant: t for t in tasks if "max_minutes" not in t.config}
    budget = {t.variant: t for t in tasks if "max_minutes" in t.config}
    assert set(steps) == set(budget) == {m.label for m, _ in bench_rows(METHODS, "gt")}
    for label, task in budget.items():
        # the cap defaults to twice the equal-step count; both runs share seed, priors and method settings
        assert task.config["max_minutes"] == 1.5 and task.config["iterations"] == 600
        assert task.out == tmp_path / "out" / "runs_budget" / "tiny" / task.out.name != steps[label].out
        assert {k: v for k, v in task.config.items() if k not in ("max_minutes", "iterations")} == \
            {k: v for k, v in steps[label].config.items() if k != "iterations"}
    capped, _ = plan_bench({"tiny": (scene, 0)}, tmp_path / "out", iterations=300, budget_minutes=2, budget_step_cap=7)
    assert {t.config["iterations"] for t in capped if "max_minutes" in t.config} == {7}


def test_several_budgets_each_get_their_folder_name_suffix_and_a_cap_scaled_by_their_minutes(tmp_path, scene):
    # the first budget keeps the folders of a one-budget bench; a repeat and a zero are dropped
    plans = budget_plan([1, 5, 0, 1, 2.5], 600)
    assert [(b.minutes, b.step_cap, b.folder, b.suffix) for b in plans] == [
        (1.0, 600, "runs_budget", "@budget"), (2.5, 1500, "runs_budget_2.5min", "@2.5min"),
        (5.0, 3000, "runs_budget_5min", "@5min")]
    # the order given changes nothing: the shortest budget has the cap and the one-budget folder
    assert budget_plan([5, 2.5, 1], 600) == plans
    assert budget_plan(0, 600) == [] and budget_plan([0], 600) == [] and len(budget_plan(2, 600)) == 1
    with pytest.raises(ConfigError, match="budget_minutes must be >= 0"):
        budget_plan([1, -5], 600)
    with pytest.raises(ConfigError, match="too close to tell apart"):
        budget_plan([1, 2.5, 2.5000001], 600)
    methods = [m for m in METHODS if m.key in ("3dgs", "esgs_depth")]
    tasks, _ = plan_bench({"tiny": (scene, 0)}, tmp_path / "out", iterations=300, methods=methods,
                          budget_minutes=[1, 5], priors="gt")
    by_name = {task.name: task for task in tasks}
    assert sorted(by_name) == ["tiny/3dgs", "tiny/3dgs@5min", "tiny/3dgs@budget",
                               "tiny/esgs_depth", "tiny/esgs_depth@5min", "tiny/esgs_depth@budget"]
    five = by_name["tiny/esgs_depth@5min"]
    assert five.config["max_minutes"] == 5.0 and five.config["iterations"] == 3000
    assert five.out == tmp_path / "out" / "runs_budget_5min" / "tiny" / "esgs_depth"
    assert by_name["tiny/esgs_depth@budget"].config["iterations"] == 600
    assert {k: v for k, v in five.config.items() if k not in ("max_minutes", "iterations")} == \
        {k: v for k, v in by_name["tiny/esgs_depth@budget"].config.items() if k not in ("max_minutes", "iterations")}


def test_rows_select_methods_in_the_tables_order_and_the_cli_names_every_row():
    import argparse

    from esgs.core.commands import bench as command

    assert [m.key for m in select_methods(["esgs_full", "3dgs"])] == ["3dgs", "esgs_full"]
    assert select_methods(None) == METHODS == select_methods([])
    with pytest.raises(ConfigError, match="'esgs_fll'") as error:
        select_methods(["3dgs", "esgs_fll"])
    assert "esgs_full_gt" in error.value.hint
    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    # the help lists the keys by hand (the CLI does not import the bench to start): it must name every row
    help_text = next(a.help for a in parser._actions if a.dest == "rows")
    listed = {word.strip(",()") for word in help_text.replace(":", " ").split()}
    assert {m.key for m in METHODS} <= listed
    args = parser.parse_args(["--out", "x", "--rows", "3dgs", "esgs_full", "--budget-minutes", "1", "5"])
    assert args.rows == ["3dgs", "esgs_full"] and args.budget_minutes == [1.0, 5.0]


def test_a_report_of_one_budget_reads_as_a_list_of_budgets_and_each_budget_gets_its_tables(tmp_path):
    from esgs.core.experiments.bench import _comparison, bench_markdown, budget_of

    old = {"budget": {"budget_minutes": 1.0, "step_cap": 1000}}
    assert report_budgets(old) == [old["budget"]] and report_budgets({"budget": None}) == []
    # runs are told apart by their folders (no task name parsing)
    tasks, _ = plan_bench({"tiny": (tmp_path, 0)}, tmp_path / "out", iterations=10, methods=METHODS[:1],
                          budget_minutes=[5, 1])
    plans = budget_plan([1, 5], 20)
    assert [(t.name, budget_of(t, tmp_path / "out", plans)) for t in tasks] == [
        ("tiny/3dgs", None), ("tiny/3dgs@budget", plans[0]), ("tiny/3dgs@5min", plans[1])]
    # a report with two budgets: one set of tables each, in order, with the steps reached
    keys = ["ssim", "psnr", "lpips", "distance_mean", "steps"]
    label = METHODS[0].label

    def run(steps, ssim):
        return {"variant": label, "scene": "tiny", "seed": 0, "ssim": ssim, "psnr": 20.0, "lpips": 0.3,
                "distance_mean": 1.0, "steps": steps}
    report = {"suite": {"name": "quick", "presets": ["cratered_plain"], "seeds": [0], "views": 10,
                        "resolution": "160x90", "samples": 8, "points_per_view": 300},
              "machine": {"platform": "p", "processor": "c", "cpu_count": 2, "python": "3", "torch": "2", "gpu": None},
              "executor": "LocalExecutor", "iterations": 10, "date": "today", "command": "esgs bench",
              "priors": None, "sparse_points": None, "notes": [], "failed": [],
              **_comparison([run(10, 0.5)], ["tiny"], keys),
              "budgets": [{"budget_minutes": 1.0, "step_cap": 20, **_comparison([run(123, 0.6)], ["tiny"], keys)},
                          {"budget_minutes": 5.0, "step_cap": 100, **_comparison([run(456, 0.7)], ["tiny"], keys)}]}
    text = bench_markdown(report)
    one, five = text.index("## At equal wall-clock budget (1 min): all scenes"), \
        text.index("## At equal wall-clock budget (5 min): all scenes")
    assert text.index("## At equal step count (10 steps): all scenes") < one < five
    assert "123" in text[one:five] and "456" in text[five:] and "0.7000" in text[five:]
    assert ("1 minutes of training (at most 20 steps), 5 minutes of training (at most 100 steps) for the "
            "equal-budget ones") in text


def test_suites_fit_their_machines():
    quick, full, large = SUITES["quick"], SUITES["full"], SUITES["large"]
    assert quick.budget_minutes > 0 and full.budget_minutes > 0 and full.step_cap == 2 * full.iterations
    # the full suite is sized for this 2-core machine; only the large one asks for more
    assert len(full.presets) * len(full.seeds) <= 6 and full.resolution == "320x180" and full.views <= 12
    assert "GPU" in large.description and large.step_cap == 30_000


@pytest.mark.slow  # two spawned workers importing torch and the rasterizer: ~25 s on 2 busy cores
def test_tiny_bench_runs_two_methods_writes_markdown_and_restarts_without_retraining(tmp_path, scene):
    methods = [m for m in METHODS if m.key in ("3dgs", "dropout_gs")]
    seen = []
    with LocalExecutor(2) as executor:
        report = run_bench(tmp_path / "bench", "quick", executor=executor, scenes={"tiny": (scene, 0)}, budget_minutes=0,
                           methods=methods, iterations=4, train=TRAIN, on_outcome=lambda o: seen.append(o.status))
    assert sorted(seen) == ["done", "done"] and report["failed"] == []
    runs = {run["variant"]: run for run in report["runs"]}
    assert set(runs) == {"3DGS", "DropoutGS"}
    for run in runs.values():
        assert run["steps"] == 4 and run["psnr"] > 0 and run["peak_memory_mib"] > 50
        assert run["render_s_per_frame"] > 0 and run["distance_mean"] > 0
    markdown = (tmp_path / "bench" / "benchmarks.md").read_text()
    assert "| DropoutGS |" in markdown and "Machine:" in markdown and "render (ms/frame)" in markdown
    assert "Priors: the ESGS rows use the `auto` priors" in markdown and "(upper bound)" in markdown
    assert "SfM points (the initial Gaussians, the sfm priors, the pinning of NDN depth): the generator's" in markdown
    assert json.loads((tmp_path / "bench" / "benchmarks.json").read_text())["iterations"] == 4
    seen.clear()
    with LocalExecutor(1) as executor:
        again = run_bench(tmp_path / "bench", "quick", executor=executor, scenes={"tiny": (scene, 0)}, budget_minutes=0,
                          methods=methods, iterations=4, train=TRAIN, on_outcome=lambda o: seen.append(o.status))
    assert seen == ["skipped", "skipped"]
    assert again["overall"] == json.loads(json.dumps(report["overall"]))
    # other settings: the old runs are stale, kept aside, and trained again
    seen.clear()
    with LocalExecutor(1) as executor:
        third = run_bench(tmp_path / "bench", "quick", executor=executor, scenes={"tiny": (scene, 0)},
                          budget_minutes=0, methods=methods, iterations=4, train={**TRAIN, "lambda_dssim": 0.3},
                          on_outcome=lambda o: seen.append(o.status))
    assert seen == ["done", "done"] and any("2 run(s) trained again" in note for note in third["notes"])
    assert len(list((tmp_path / "bench" / "runs" / "tiny").glob("*.stale-*"))) == 2


def test_a_run_that_keeps_failing_is_reported_in_the_markdown(tmp_path, scene):
    methods = [m for m in METHODS if m.key == "3dgs"]
    with LocalExecutor(1) as executor:
        report = run_bench(tmp_path / "bench", "quick", executor=executor, scenes={"tiny": (scene, 0)}, budget_minutes=0,
                           methods=methods, iterations=4, train={**TRAIN, "sh_degree": 7})
    assert len(report["failed"]) == 1 and report["failed"][0]["attempts"] == 2
    assert "sh_degree" in report["failed"][0]["error"]
    assert "FAILED tiny/3dgs after 2 attempts" in (tmp_path / "bench" / "benchmarks.md").read_text()


def test_cli_passes_the_prior_sources_and_the_sparse_points_to_the_bench(monkeypatch):
    import argparse

    from esgs.core.commands import bench as command
    from esgs.core.experiments import bench

    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    choices = next(a for a in parser._actions if a.dest == "priors").choices
    assert set(choices) == set(PRIOR_CHOICES)
    args = parser.parse_args(["--out", "x"])
    assert args.priors == ["auto"] and args.sparse_points == "triangulated"
    seen = {}
    monkeypatch.setattr(bench, "run_bench", lambda out, suite, **kwargs: seen.update(kwargs) or {"failed": []})
    command.run(parser.parse_args(["--out", "x", "--priors", "auto", "labels", "ndn", "--sparse-points", "exact",
                                   "--executor", "local"]))
    assert seen["priors"] == ["auto", "labels", "ndn"] and seen["sparse_points"] == "exact"


def test_cli_keeps_the_local_pool_for_quick_and_uses_ray_for_the_big_suites_and_an_address():
    import argparse

    from esgs.core.commands import bench as command

    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    kind = lambda *argv: command.executor_kind(parser.parse_args(["--out", "x", *argv]))  # noqa: E731
    assert kind() == "local" and kind("--suite", "quick", "--workers", "2") == "local"
    assert kind("--suite", "full") == "ray" and kind("--suite", "large") == "ray"
    assert kind("--address", "auto") == "ray" and kind("--suite", "full", "--executor", "local") == "local"
    args = parser.parse_args(["--out", "x", "--budget-minutes", "0", "--budget-step-cap", "40"])
    assert args.budget_minutes == [0] and args.budget_step_cap == 40
    with pytest.raises(ConfigError, match="--address"):
        command.run(parser.parse_args(["--out", "x", "--address", "auto", "--executor", "local"]))


def test_make_scene_triangulates_the_rendered_images_and_caches_both_folders(tmp_path, monkeypatch):
    from esgs.core.colmap import read_model
    from esgs.core.experiments import sfm_scene
    from esgs.core.experiments.bench import _sparse_points_description, _sparse_points_sentence, make_scene
    from esgs.core.terrain import scene_job

    from .test_acceptance import _textured_plane_scene

    suite, scenes = SUITES["quick"], tmp_path / "scenes"
    # the render is cached: make_scene starts from it and never calls Blender
    rendered, _ = _textured_plane_scene(scenes / suite.scene_folder_name("plane", 0, "exact"))
    monkeypatch.setattr(scene_job, "render_scene", lambda *a, **k: pytest.fail("the render should be reused"))
    folder = make_scene("plane", 0, suite, scenes)
    assert folder == scenes / suite.scene_folder_name("plane", 0) and folder.name.endswith("_sfm")
    assert folder.name == "plane_s0_10v_160x90_8spp_sfm" and rendered.name == "plane_s0_10v_160x90_8spp_300p"
    points = read_model(folder).points
    assert len(points) > 100 and not read_model(rendered).points  # triangulated, where the render had none
    assert (folder / "priors" / "sfm" / "depth").is_dir()  # the sfm priors come from those points
    record = json.loads((folder / "scene.json").read_text())["sparse_points"]
    assert record["points"] == len(points)
    # both folders are reused: no second triangulation
    monkeypatch.setattr(sfm_scene, "make_sfm_scene", lambda *a, **k: pytest.fail("the scene should be reused"))
    assert make_scene("plane", 0, suite, scenes) == folder
    assert make_scene("plane", 0, suite, scenes, "exact") == rendered
    with pytest.raises(ConfigError, match="sparse points"):
        make_scene("plane", 0, suite, scenes, "surface")
    # the report says where the points came from
    described = _sparse_points_description({"plane": (folder, 0)})
    assert described["kind"] == "triangulated" and described["points"] == {"plane": len(points)}
    assert "triangulated from the rendered images" in _sparse_points_sentence(described, 300)
    exact = _sparse_points_description({"plane": (rendered, 0)})
    assert exact["kind"] == "exact" and "exact surface samples (300 per view)" in _sparse_points_sentence(exact, 300)
    assert _sparse_points_description({"a": (folder, 0), "b": (rendered, 0)})["kind"] == "mixed"


def test_a_run_made_on_another_scene_folder_is_stale(tmp_path, scene):
    from esgs.core.config import config_to_dict
    from esgs.core.methods import train_config_from_dict

    task = RunTask(name="tiny/3dgs", scene=scene, out=tmp_path / "run", config={**TRAIN, "iterations": 5, "seed": 0})
    saved = config_to_dict(train_config_from_dict({**task.config, "scene": str(scene), "out": str(task.out)},
                                                  saved=False))
    task.out.mkdir()

    def saved_on(folder):
        (task.out / "config.json").write_text(json.dumps({**saved, "scene": str(folder)}))
        return task.stale_settings()

    assert saved_on(scene) == [] and saved_on(tmp_path / "moved" / scene.name) == []  # a moved bench keeps its runs
    assert saved_on(scene.with_name(f"{scene.name}_sfm")) == ["scene"]  # exact points -> triangulated: trained again
    assert saved_on(tmp_path / "esgs_run_x1" / "scene") == []  # shipped before runs kept the scene's name: unknown


def test_a_shipped_run_trains_on_a_scratch_copy_under_the_scene_name(tmp_path, scene):
    from esgs.core.experiments.executor import _run_shipped, pack_folder

    task = RunTask(name="tiny/3dgs", scene=scene, out=tmp_path / "run", config={})
    ok, value, _ = _run_shipped(_scene_of, task, pack_folder(scene))
    assert ok and value[0] == scene.name and value[1]


def _scene_of(task):
    return Path(task.scene).name, (Path(task.scene) / "sparse").is_dir()


def test_equal_step_runs_record_evaluation_curves_and_the_report_times_3dgs_quality(tmp_path, scene):
    methods = [m for m in METHODS if m.key in ("3dgs", "3dgs_sky", "dropout_gs")]
    with LocalExecutor(1) as executor:
        report = run_bench(tmp_path / "bench", "quick", executor=executor, scenes={"tiny": (scene, 0)},
                           budget_minutes=0, methods=methods, iterations=4, eval_every=2, train=TRAIN)
    assert report["failed"] == []
    part = report["time_to_baseline"]
    assert part["baseline"] == "3DGS" and part["eval_every"] == 2 and part["missing_baseline"] == []
    runs = {run["variant"]: run for run in part["runs"]}
    assert set(runs) == {"3DGS", "3DGS + sky model (our defaults)", "DropoutGS"}
    assert all(run["points"] == 2 for run in runs.values())
    # and against 3DGS as plain `esgs train` gives it, the run `esgs train --esgs` is compared with
    defaults = report["time_to_defaults"]
    assert defaults["baseline"] == "3DGS + sky model (our defaults)"
    own = {run["variant"]: run for run in defaults["runs"]}["3DGS + sky model (our defaults)"]
    sky_summary = {run["variant"]: run for run in report["runs"]}["3DGS + sky model (our defaults)"]
    assert own["target_psnr"] == pytest.approx(sky_summary["psnr"])
    baseline = runs["3DGS"]
    summary = {run["variant"]: run for run in report["runs"]}["3DGS"]
    assert baseline["target_psnr"] == pytest.approx(summary["psnr"])
    assert baseline["target_ssim"] == pytest.approx(summary["ssim"])
    assert 0 < baseline["baseline_s"] == pytest.approx(summary["train_s"])  # both training seconds only
    assert baseline["to_quality_s"] <= baseline["baseline_s"]
    config = json.loads((tmp_path / "bench" / "runs" / "tiny" / "3dgs" / "config.json").read_text())
    assert config["eval_every"] == 2
    markdown = (tmp_path / "bench" / "benchmarks.md").read_text()
    assert "## Time to 3DGS's quality: all scenes" in markdown and "### Time to 3DGS's quality: tiny" in markdown
    assert "evaluated every 2 steps" in markdown and "| DropoutGS | 1 |" in markdown
    assert "## Time to 3DGS + sky model (our defaults)'s quality: all scenes" in markdown
    # a reused bench folder with another eval_every keeps its runs (evaluating changes no training)
    seen = []
    with LocalExecutor(1) as executor:
        again = run_bench(tmp_path / "bench", "quick", executor=executor, scenes={"tiny": (scene, 0)},
                          budget_minutes=0, methods=methods, iterations=4, eval_every=0, train=TRAIN,
                          on_outcome=lambda o: seen.append(o.status))
    assert seen == ["skipped", "skipped", "skipped"]
    assert again["time_to_baseline"]["runs"] == json.loads(json.dumps(part["runs"]))


def test_eval_every_goes_to_the_equal_step_runs_only_and_defaults_to_a_tenth_of_the_run(tmp_path, scene):
    tasks, _ = plan_bench({"tiny": (scene, 0)}, tmp_path, iterations=40, methods=METHODS[:1], budget_minutes=1.0,
                          eval_every=4)
    assert {task.name: task.config.get("eval_every") for task in tasks} == {"tiny/3dgs": 4, "tiny/3dgs@budget": None}
    tasks, _ = plan_bench({"tiny": (scene, 0)}, tmp_path, iterations=40, methods=METHODS[:1])
    assert "eval_every" not in tasks[0].config  # 0: the runs' configs as before
    assert [SUITES[name].eval_every() for name in ("quick", "full", "large")] == [30, 50, 700]
    assert SUITES["quick"].eval_every(2000) == 200


def test_the_time_to_quality_table_says_not_reached_and_counts_runs_without_a_curve():
    from esgs.core.experiments.bench import _time_to_baseline_markdown
    from esgs.core.experiments.curves import EvalPoint, time_to_baseline_quality

    runs = [{"key": "3dgs", "variant": "3DGS", "scene": "s", "seed": 0,
             "curve": [EvalPoint(5, 1.0, 20.0, 0.6), EvalPoint(10, 2.0, 22.0, 0.7)]},
            {"key": "esgs", "variant": "ESGS", "scene": "s", "seed": 0, "curve": [EvalPoint(10, 3.0, 21.0, 0.8)]}]
    part = {"baseline": "3DGS", "eval_every": 0, **time_to_baseline_quality(runs, "3dgs")}
    markdown = "\n".join(_time_to_baseline_markdown(part, 10))
    assert "| ESGS | 1 | 2.0 | not reached | 3.0 | not reached | not reached |" in markdown
    assert "| 3DGS | 1 | 2.0 | 2.0 | 2.0 | 2.0 | 1.00 |" in markdown
    assert "1 run(s) have a single evaluation" in markdown and "end-of-run evaluation only" in markdown


def test_cli_passes_eval_every(monkeypatch):
    import argparse

    from esgs.core.commands import bench as command
    from esgs.core.experiments import bench

    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    assert parser.parse_args(["--out", "x"]).eval_every is None  # the suite's
    seen = {}
    monkeypatch.setattr(bench, "run_bench", lambda out, suite, **kwargs: seen.update(kwargs) or {"failed": []})
    command.run(parser.parse_args(["--out", "x", "--eval-every", "25", "--executor", "local"]))
    assert seen["eval_every"] == 25
