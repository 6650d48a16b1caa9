"""core/formats/scene_dir.py: the prior sources' facts against what their writers really put on disk,
the scene-folder paths, and one owner for the file names of scene and run folders."""
from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest

from esgs.core.errors import ConfigError
from esgs.core.formats.imageio import read_depth_exr, read_normal_exr
from esgs.core.priors import load_prior_maps
from esgs.core.formats.scene_dir import PriorSource, SceneDir, names
from esgs.core.formats.run_dir import RunDir

from .ndn.conftest import make_scene, tiny_config

REPO = Path(__file__).resolve().parents[2]


def _written_facts(scene: Path, source: PriorSource, image_name: str) -> dict:
    """What the files of ``source`` for one view say about themselves."""
    folder = SceneDir(scene)
    depth_path = folder.depth_map(source, image_name)
    _, header = read_depth_exr(depth_path)
    return {"mask": folder.mask_map(source, image_name).is_file(),
            "normals": folder.normal_map(source, image_name).is_file(),
            "mask_kind": header.get("mask_kind"), "depth_kind": header.get("depth_kind"),
            "sky": load_prior_maps(scene, source, image_name).sky is not None}


def _expected(source: PriorSource) -> dict:
    return {"mask": source.has_mask, "normals": source.has_normals, "mask_kind": source.mask_kind,
            "depth_kind": source.depth_kind, "sky": source.masks_sky}


def test_sfm_facts_match_what_write_sfm_priors_writes(tmp_path):
    from esgs.core.colmap import read_model
    from esgs.core.priors.sfm import write_sfm_priors

    scene = make_scene(tmp_path / "scene", views=2, with_gt=False)
    write_sfm_priors(scene, read_model(scene))
    assert _written_facts(scene, PriorSource.SFM, "view_000.png") == _expected(PriorSource.SFM)


def test_ndn_facts_match_what_write_ndn_priors_writes(tmp_path):
    import torch

    from esgs.core.ndn.infer import write_ndn_priors
    from esgs.core.ndn.train import build_model, save_checkpoint

    scene = make_scene(tmp_path / "scene", views=1, with_gt=False)
    torch.manual_seed(0)
    model, _ = build_model(tiny_config())
    weights = save_checkpoint(tmp_path / "weights.pt", model, tiny_config())
    write_ndn_priors(scene, weights, steps=1)
    facts = _written_facts(scene, PriorSource.NDN, "view_000.png")
    assert facts == _expected(PriorSource.NDN)
    assert facts["depth_kind"] == "relative" and facts["sky"]


def test_labels_facts_match_what_the_label_writer_writes(tmp_path):
    from esgs.core.labels.writer import LabelWriter

    scene = make_scene(tmp_path / "scene", views=1, with_gt=False)
    depth = np.full((27, 48), 4.0, np.float32)
    depth[:3] = 0.0  # no mesh there
    normal = np.broadcast_to(np.array([0.0, 0.0, -1.0], np.float32), (27, 48, 3)).copy()
    with LabelWriter(scene, {"mesh": "plane", "method": "mesh"}) as writer:
        writer.add("view_000.png", depth, normal)
    assert _written_facts(scene, PriorSource.LABELS, "view_000.png") == _expected(PriorSource.LABELS)
    report = json.loads(SceneDir(scene).labels_report.read_text())
    assert report["source"] == "labels" and len(report["views"]) == 1


def test_gt_and_sky_filled_facts_match_the_files_without_a_mask_kind_header(tmp_path):
    """Blender's scene renderer writes gt EXRs with no ``mask_kind`` header (esgs_addon/render_dataset.py),
    so the source's own kind decides: the gt mask marks sky."""
    from esgs.core.formats.imageio import write_depth_exr, write_normal_exr, write_png

    scene = SceneDir(tmp_path)
    mask = np.ones((8, 8), bool)
    mask[:2] = False
    for source in (PriorSource.GT, PriorSource.GT_SKYFILLED):
        write_depth_exr(scene.depth_map(source, "a.png"), np.where(mask, 3.0, 0.0).astype(np.float32), units="m")
        write_normal_exr(scene.normal_map(source, "a.png"), np.zeros((8, 8, 3), np.float32) + [0, 0, -1.0])
        write_png(scene.mask_map(source, "a.png"), np.where(mask, 255, 0).astype(np.uint8))
        maps = load_prior_maps(tmp_path, source, "a.png")
        assert (maps.sky is not None) == source.masks_sky
        assert maps.relative_depth == source.relative_depth
        assert (maps.normal is not None) == source.has_normals


def test_the_fixture_scene_gt_uses_the_standard_layout(tmp_path):
    scene = make_scene(tmp_path / "scene", views=2)
    folder = SceneDir(scene)
    assert folder.model.is_dir() and folder.image("view_001.png").is_file() and folder.has_model()
    for kind in ("depth", "normal", "mask"):
        assert folder.has_prior_maps(PriorSource.GT, kind)
    _, header = read_normal_exr(folder.normal_map(PriorSource.GT, "view_001.png"))
    assert header["source"] == "gt"


def test_the_lists_every_caller_used_are_derived_from_the_enum():
    from esgs.core.commands import priors as priors_command
    from esgs.core.apps.demo import PRIOR_SOURCES as DEMO_SOURCES
    from esgs.core.experiments import ablate, bench
    from esgs.core.train.dataset import find_mask_source

    assert names(PriorSource.standard_sources()) == ("gt", "labels", "ndn", "sfm", "auto") == ablate.DEFAULT_PRIOR_ORDER
    assert names(PriorSource.single_sources()) == ("gt", "labels", "ndn", "sfm")
    assert ablate.PRIOR_SOURCES == ("none", "auto", "sfm", "ndn", "labels", "gt")
    assert DEMO_SOURCES == bench.PRIOR_SOURCES == ("ndn", "sfm", "auto", "gt")
    assert bench.COMPUTED_PRIOR_SOURCES == ("ndn", "sfm", "auto")
    assert set(priors_command.METHODS) == {"ndn", "sfm", "auto"}
    assert bench.ENSURED_PRIOR_SOURCES == ("ndn", "sfm", "auto", "labels")
    # sfm's mask marks sparse samples only: never an automatic photometric mask
    assert names(PriorSource.auto_mask_order()) == ("gt", "labels", "ndn")
    assert find_mask_source  # the dataset's auto choice walks auto_mask_order (tests/core/train/test_dataset.py)
    assert [s.value for s in PriorSource if s.masks_sky] == ["gt", "ndn", "gt_skyfilled"]
    assert [s.value for s in PriorSource if not s.has_normals] == ["sfm"]
    assert [s.value for s in PriorSource if s.relative_depth] == ["ndn"]
    assert [s.value for s in PriorSource if s.made_by_labels] == ["labels"]
    assert [s.value for s in PriorSource if s.made_by_scene] == ["gt"]
    assert [s.value for s in PriorSource if s.fused] == ["auto"]


def test_members_are_plain_strings_in_json_paths_and_messages(tmp_path):
    assert json.dumps({"priors": PriorSource.NDN}) == '{"priors": "ndn"}'
    assert f"{PriorSource.SFM}" == str(PriorSource.SFM) == "sfm" and PriorSource("gt") is PriorSource.GT
    assert SceneDir(tmp_path).prior(PriorSource.LABELS) == tmp_path / "priors" / "labels"
    assert PriorSource.parse("ndn") is PriorSource.NDN
    with pytest.raises(ConfigError, match="use one of gt, labels, ndn, sfm"):
        PriorSource.parse("gt_skyfilled")
    assert PriorSource.parse("gt_skyfilled", tuple(PriorSource)) is PriorSource.GT_SKYFILLED


def test_scene_dir_spells_the_folder_conventions(tmp_path):
    scene = SceneDir(tmp_path)
    relative = {name: getattr(scene, name).relative_to(tmp_path).as_posix() for name in (
        "images", "sparse", "model", "sfm_model", "priors", "mesh", "ground_truth_mesh", "reconstructed_mesh",
        "reconstruction_report", "reconstructed_gaps", "provenance", "labels_report", "labels_accuracy")}
    assert relative == {
        "images": "images", "sparse": "sparse", "model": "sparse/0", "sfm_model": "sparse_sfm/0", "priors": "priors",
        "mesh": "mesh", "ground_truth_mesh": "mesh/ground_truth.ply", "reconstructed_mesh": "mesh/reconstructed.ply",
        "reconstruction_report": "mesh/reconstructed.json", "reconstructed_gaps": "mesh/reconstructed_gaps.ply",
        "provenance": "scene.json", "labels_report": "priors/labels/labels.json",
        "labels_accuracy": "priors/labels/accuracy.json"}
    assert scene.depth_map("ndn", "sub/a.b.png") == tmp_path / "priors/ndn/depth/sub/a.b.exr"
    assert scene.normal_map("gt", "x.jpg") == tmp_path / "priors/gt/normal/x.exr"
    assert scene.mask_map("gt", "x.jpg") == tmp_path / "priors/gt/mask/x.png"
    with pytest.raises(ValueError):
        scene.prior_maps("gt", "colour")
    assert not scene.has_model() and SceneDir(str(tmp_path)).root == tmp_path


def test_run_dir_spells_the_run_folder(tmp_path):
    run = RunDir(tmp_path)
    assert {name: getattr(run, name).relative_to(tmp_path).as_posix() for name in (
        "config", "checkpoints", "point_cloud", "metrics", "renders", "test_renders", "events", "result",
        "stop_request")} == {
        "config": "config.json", "checkpoints": "checkpoints", "point_cloud": "point_cloud.ply",
        "metrics": "metrics.json", "renders": "renders", "test_renders": "renders/test", "events": "events.jsonl",
        "result": "train_result.json", "stop_request": "STOP"}
    assert run.test_render("v1") == tmp_path / "renders/test/v1.png"
    assert not run.has_checkpoints()
    (tmp_path / "checkpoints").mkdir()
    assert run.has_checkpoints()


# --------------------------------------------------------------------------- one owner per name

#: file names of scene and run folders: any string constant equal to one of them is a spelling
FILE_NAMES = {"ground_truth.ply", "scene.json", "labels.json", "accuracy.json", "reconstructed.ply",
              "reconstructed_gaps.ply", "reconstructed.json", "config.json", "metrics.json", "point_cloud.ply",
              "events.jsonl", "train_result.json"}
#: folder names: a spelling when joined with ``/`` to a path (they are common words elsewhere)
FOLDER_NAMES = {"images", "sparse", "sparse_sfm", "priors", "mesh", "checkpoints", "renders"}
OWNERS = {"core/formats/scene_dir.py", "core/formats/run_dir.py"}
#: files allowed to spell those names, each with the reason
ALLOWED = {
    # another folder's layout, not a scene or run folder
    "core/ndn/train.py": "the NDN model folder (MODEL_DIR: config.json, checkpoints/, events.jsonl) is its own layout",
    "core/commands/ndn.py": "the NDN model folder's events.jsonl",
    "benchmarks/ship_ndn.py": "the NDN model folder's config.json and events.jsonl (its navcam scene's "
                              "sparse/ and images/ checks are still to convert)",
    "benchmarks/bench_import_gaussians.py": "times a PLY write into a temporary folder, not a run folder",
    "core/runtime/process.py": "a job's exchange folder (job_config.json, job_result.json, job_stop, events.jsonl) "
                               "is its own layout, and the runtime sits below the training layer (RunDir)",
}
#: spellings still to route through SceneDir/RunDir (issue #21 item 4): none left; a file that
#: cannot be converted yet goes here with the reason
TO_CONVERT: dict[str, str] = {}


def _spellings(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
                  and node.body and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings \
                and node.value in FILE_NAMES:
            found.append(f"{path.relative_to(REPO)}:{node.lineno}: {node.value!r}")
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            for side in (node.left, node.right):
                if isinstance(side, ast.Constant) and side.value in FOLDER_NAMES:
                    found.append(f"{path.relative_to(REPO)}:{side.lineno}: / {side.value!r}")
    return found


def test_only_scene_dir_and_run_dir_spell_folder_file_names():
    offenders = []
    for folder in ("core", "esgs_addon", "operators", "panels", "benchmarks", "examples"):
        for path in sorted((REPO / folder).rglob("*.py")):
            relative = path.relative_to(REPO).as_posix()
            if relative in OWNERS or relative in ALLOWED or relative in TO_CONVERT:
                continue
            offenders += _spellings(path)
    assert not offenders, "spell these through SceneDir / RunDir:\n" + "\n".join(offenders)


def test_the_allow_lists_name_files_that_exist_and_still_spell_names():
    for relative in (*ALLOWED, *TO_CONVERT):
        path = REPO / relative
        assert path.is_file(), relative
        assert _spellings(path), f"{relative} no longer spells a folder name: take it off the allow-list"
