"""Ship the completion network as the package's normals network, in one command.

    .venv/bin/python benchmarks/ship_completion.py benchmarks/weights/completion_2026-11-29_step2000.pt \\
        [--work /work/runs/hf/work] [--card-only] [--fine-tune TRAINING_JSON] [--evaluation EVALUATION_JSON] \\
        [--navcam NAVCAM_SKY_JSON]

It (1) copies the float16 weights (or exports a training checkpoint) to
``core/ndn/weights/ndn_completion.pt``, (2) cuts a three-view slice with its evidence (SfM cells
and stereo labels at the working size) from the prepared report scenes of
``benchmarks/ndn_completion.py`` once (then keeps it) in ``tests/core/fixtures/ndn/``, (3) scores
the shipped file on it with that evidence and writes the expected scores, and (4) writes
``docs/ndn_completion_model_card.md`` from the training record and the full-image evaluation in
``benchmarks/results/``. ``tests/core/ndn/test_shipped.py`` then re-scores the slice and compares
with the card.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
FIXTURE_DIR = REPO / "tests" / "core" / "fixtures" / "ndn"
SLICE = FIXTURE_DIR / "completion_slice.npz"
SLICE_SCORES = FIXTURE_DIR / "completion_slice_scores.json"
CARD = REPO / "docs" / "ndn_completion_model_card.md"
TRAINING = REPO / "benchmarks" / "results" / "ndn_completion_training_2026-11-29.json"
EVALUATION = REPO / "benchmarks" / "results" / "ndn_completion_hybrid_2026-11-29.json"
# (original scene, view) of the slice: one view of each report set but the varied rover looks
SLICE_PICKS = (("/work/runs/hf/scenes/plain_100000", 3), ("/work/runs/hf/scenes/landform_201", 12),
               ("/work/runs/hf/scenes/rover_100100", 2))
SLICE_KEYS = ("views", "depth", "normal", "mask", "sfm_depth", "stereo_depth")
SCORES = ("normal_mean_deg", "normal_within_11_25", "abs_rel_metric", "delta1_metric")
SEED = 0


def fmt(key: str, value: float) -> str:
    """The card's number format (the test formats its expectation the same way)."""
    return f"{value:.2f}" if key == "normal_mean_deg" else f"{100 * value:.1f} %" if key.startswith(("normal_w", "delta")) \
        else f"{value:.4f}"


def cut_slice(work: Path) -> None:
    """The slice's arrays from the prepared scene copies (``benchmarks/ndn_completion.py``'s cache)."""
    from ndn_completion import scene_views

    parts: dict[str, list] = {key: [] for key in SLICE_KEYS + ("names",)}
    for scene, view in SLICE_PICKS:
        scene = Path(scene)
        data = scene_views(scene, work / f"{scene.name}_sfm")
        for key in SLICE_KEYS:
            parts[key].append(data[key][view])
        parts["names"].append(f"{scene.name}/{data['names'][view]}")
    FIXTURE_DIR.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(SLICE, **{key: np.stack(values) for key, values in parts.items()})


def score_slice(weights: Path) -> dict:
    import torch

    from esgs.core.ndn.checkpoint import load_checkpoint
    from esgs.core.ndn.infer import evaluate_arrays, mean_scores

    with np.load(SLICE, allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files}
    names = [str(name) for name in arrays.pop("names")]
    model, diffusion, _, payload = load_checkpoint(weights)
    torch.set_num_threads(1)
    scores = mean_scores(evaluate_arrays(model, diffusion, arrays, seed=SEED, evidence_mode="sfm_stereo"))
    return {"weights_sha256": hashlib.sha256(weights.read_bytes()).hexdigest(), "step": int(payload["step"]),
            "seed": SEED, "evidence": "sfm_stereo", "names": names,
            "scores": {key: scores[key] for key in SCORES}}


def _row(rows: dict, name: str) -> str:
    scores = rows[name]["all"]
    return f"{scores['abs_rel_metric']:.3f} / {scores['delta1_metric']:.3f} / {scores['normal_mean_deg']:.1f}"


def card(weights: Path, slice_scores: dict, *, evaluation_path: Path = EVALUATION, fine_tune: Path | None = None,
         navcam: Path | None = None) -> str:
    """The model card's text. ``fine_tune``: the training record of a continuation of the base run
    (its config, CPU hours and why); ``navcam``: ``benchmarks/ndn_sky_masks.py``'s result, whose
    ``shipped`` entry says how much of the real Navcam frames' sky the shipped file finds."""
    from esgs.core.ndn.checkpoint import load_checkpoint
    from esgs.core.ndn.model import parameter_count

    training = json.loads(TRAINING.read_text())
    evaluation = json.loads(evaluation_path.read_text())
    model, _, config, payload = load_checkpoint(weights)
    sets = evaluation["sets"]
    labels = {"heldout": "held-out synthetic", "landform": "real mesh (landform)", "rover": "rover horizon",
              "rover_varied": "rover, varied looks"}
    rows = [("stereo labels + the hole filling before this network", "stereo_filled"),
            ("`auto` with the shipped depth network alone", "shipped:auto"),
            ("`auto` with this network alone (depth and normals)", "cand:auto"),
            ("**`auto` as shipped: the depth network's depth, this network's normals**", "shipped+cand_normals:auto")]
    lines = [
        "# Completion network model card (the normals network shipped in `core/ndn/weights/ndn_completion.pt`)", "",
        "Generated by `benchmarks/ship_completion.py`; `tests/core/ndn/test_shipped.py` re-scores the test slice "
        "against this card.", "",
        "## What it does in the product", "",
        "`esgs priors --method ndn` (and so `priors/auto`, the default prior of `esgs train --esgs`) runs two "
        "networks: the diffusion NDN (`ndn_mars.pt`, docs/ndn_model_card.md) writes depth and the surface mask; "
        "this network writes the **normals** wherever it sees a surface, and the **sky** (probability above one "
        "half), which the trainer then takes as its sky mask on scenes without ground truth. It reads, besides "
        "the three views, the view's SfM points and (when `priors/labels` exists) its stereo labels. Its depth "
        "is written as the views' second depth, which `priors/auto` blends into the stereo labels' holes of "
        "views with sky only when asked (`blend_second_depth`, off by default since ESGS trained on it left far "
        "outliers off a real mesh; alone it measured worse than the NDN's on two of the four sets below: "
        "docs/ndn.md, \"The completion network's depth, blended under the horizon\").", "",
        "## Model", "",
        f"- UNet, {parameter_count(model):,} parameters, working size {config.model.working_size} px, "
        f"{config.model.levels} levels, base width {config.model.base_channels}; inputs: three views, the SfM "
        "depth cells and the stereo labels with their validity (the evidence), outputs: depth (log state, metric "
        "through the evidence's reference depth), camera-frame normals and a sky logit;",
        f"- one regression pass per view (`prediction = {config.diffusion.prediction}`), deterministic;",
        f"- stored in float16 ({weights.stat().st_size / 1e6:.1f} MB), the training run's weight average at "
        f"training step **{int(payload['step'])}**.", "",
        "## Training", "",
        f"- data: `{training['config']['data']}` (synthetic presets with rover-height and aerial rigs, sky, "
        "varied palettes, landform-mesh views from rigs and areas kept out of evaluation, SfM triangulated from "
        "the renders; commands in docs/ndn.md, \"Retraining\");",
        f"- {training['config']['train']['steps']} steps, batch {training['config']['train']['batch_size']}, "
        f"learning rate {training['config']['train']['learning_rate']} (cosine), evidence dropped at random "
        "per sample; 3.7 CPU-hours on 2 threads; the step was chosen on the validation score of the tuning set "
        "alone;",
        f"- record: `{TRAINING.relative_to(REPO)}`.", *_fine_tune_lines(fine_tune), "",
        "## Full-image scores (every surface pixel; metric AbsRel / δ1, no alignment / normal mean error in "
        "degrees)", "",
        f"From `{evaluation_path.resolve().relative_to(REPO)}` (command inside; none of these scenes was trained on). The "
        "evaluation ran the training checkpoint; the shipped file is its float16 export (the slice below is "
        "scored with the shipped file).", "",
        "| row | " + " | ".join(f"{labels.get(name, name)} ({len(sets[name]['views'])} views)" for name in sets) + " |",
        "|---|" + "---|" * len(sets)]
    # the "before" row comes from the evaluation made before any normals network shipped: a later
    # run's cached scenes re-predict the package's own priors/ndn with the shipped network
    before = json.loads(EVALUATION.read_text())["sets"]
    for label, key in rows:
        source = before if key == "stereo_filled" else sets
        lines.append(f"| {label} | " + " | ".join(_row(source[name]["rows"], key) for name in sets) + " |")
    lines += ["", "## Test slice", "",
              f"Three views with their evidence (`{SLICE.relative_to(REPO)}`: "
              + ", ".join(f"`{name}`" for name in slice_scores["names"]) + "), this file, `sfm_stereo` evidence, "
              f"seed {slice_scores['seed']}:", "",
              "| slice | " + " | ".join(SCORES) + " |", "|---|" + "---|" * len(SCORES),
              "| completion_slice | " + " | ".join(fmt(key, slice_scores["scores"][key]) for key in SCORES) + " |",
              "", "## Limits", "",
              "- trained on synthetic scenes and one real mesh only; " + _navcam_line(navcam),
              "- the normals are in the camera frame of each view at 128 px, brought to the image size by an "
              "image-guided filter: thin structures below a few pixels at 128 px are smoothed.", "",
              "## Reproduce", "", "```",
              f"{sys.executable.replace(str(REPO) + '/', '')} benchmarks/ship_completion.py {weights_argument(weights)}",
              "```", ""]
    return "\n".join(lines)


def _fine_tune_lines(record: Path | None) -> list[str]:
    """The card's lines for continuations of the base run: a record with ``stages`` (each with
    the ``config`` of its ``esgs ndn train`` run, ``steps_run`` and ``cpu_hours``) and ``why``."""
    if record is None:
        return []
    fine = json.loads(record.read_text())
    parts = []
    for stage in fine["stages"]:
        train = stage["config"]["train"]
        flags = ", ".join(f"`--{name.replace('_', '-')} {train[name]}`" for name in ("sky_looks", "monocular", "augment")
                          if train.get(name))
        parts.append(f"to step {train['steps']} ({stage['steps_run']} steps, learning rate {train['learning_rate']} "
                     f"cosine, {flags})")
    cpu_hours = sum(stage["cpu_hours"] for stage in fine["stages"])
    return [f"- then continued {'; then '.join(parts)}: {fine['why']}; {cpu_hours:.1f} CPU-hours on 2 threads; "
            f"record: `{record.resolve().relative_to(REPO)}`."]


def _navcam_line(result: Path | None) -> str:
    if result is None:
        return "the real Navcam frames were not in training and its sky head does not find their sky (docs/ndn.md);"
    shipped = json.loads(result.read_text())["results"]["shipped"]
    return (f"the real Navcam frames were not in training; on them its sky covers {100 * shipped['recall']:.0f} % of "
            f"the sky a brightness rule marks (precision {100 * shipped['precision']:.0f} %, sky marked on "
            f"{shipped['frames_with_any_sky_marked']} of {shipped['frames_with_sky']} frames with sky; "
            f"`{result.resolve().relative_to(REPO)}`, docs/ndn.md);")


def weights_argument(weights: Path) -> str:
    try:
        return str(weights.resolve().relative_to(REPO))
    except ValueError:
        return str(weights)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("weights", type=Path, help="float16 weights file, or a training checkpoint to export")
    parser.add_argument("--work", type=Path, default=Path("/work/runs/hf/work"),
                        help="benchmarks/ndn_completion.py's prepared scene copies (only to cut the slice once)")
    parser.add_argument("--card-only", action="store_true", help="rewrite the card from the slice scores on file")
    parser.add_argument("--evaluation", type=Path, default=EVALUATION,
                        help="benchmarks/ndn_completion.py's JSON with the shipped+cand_normals:auto row")
    parser.add_argument("--fine-tune", type=Path, default=None, help="training record of a continuation")
    parser.add_argument("--navcam", type=Path, default=None, help="benchmarks/ndn_sky_masks.py's JSON")
    args = parser.parse_args()
    from esgs.core.ndn.shipped import SHIPPED_NORMAL_WEIGHTS, export_weights

    if not args.card_only:
        import torch

        payload = torch.load(args.weights, map_location="cpu", weights_only=True)
        if "optimizer" in payload or payload.get("dtype") != "float16":
            export_weights(args.weights, SHIPPED_NORMAL_WEIGHTS, provenance={"source": str(args.weights)})
        elif args.weights.resolve() != SHIPPED_NORMAL_WEIGHTS.resolve():
            shutil.copyfile(args.weights, SHIPPED_NORMAL_WEIGHTS)
        if not SLICE.exists():
            cut_slice(args.work)
        SLICE_SCORES.write_text(json.dumps(score_slice(SHIPPED_NORMAL_WEIGHTS), indent=2) + "\n")
    CARD.write_text(card(SHIPPED_NORMAL_WEIGHTS, json.loads(SLICE_SCORES.read_text()), evaluation_path=args.evaluation,
                         fine_tune=args.fine_tune, navcam=args.navcam))
    print(f"wrote {CARD}" if args.card_only else f"wrote {SHIPPED_NORMAL_WEIGHTS}, {SLICE_SCORES} and {CARD}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
