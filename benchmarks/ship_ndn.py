"""Ship an NDN training checkpoint as the package's default weights, in one command.

    .venv/bin/python benchmarks/ship_ndn.py /work/runs/ndn_model/checkpoints/step_<N>.pt \\
        [--data /work/runs/ndn_data] [--landform /work/runs/ndn_landform] \\
        [--baselines benchmarks/results/ndn_baselines.json]

It (1) writes ``core/ndn/weights/ndn_mars.pt`` (float16, no optimiser state), (2) scores
those shipped weights on every held-out triple of DATA (and of the landform set when it
exists), exactly as ``esgs ndn eval`` does, (3) rescores the small held-out slice the tests
keep in ``tests/core/fixtures/ndn/`` (the slice's arrays are cut once, from DATA, and then
kept) and writes its expected scores, (4) redraws the Navcam figures in ``docs/images/``
when the registered station exists (``--navcam``), and (5) regenerates
``docs/ndn_model_card.md`` with the data, steps, training time, held-out scores, the
baselines from ``--baselines`` and the commands that reproduce everything. ``tests/core/ndn/test_shipped.py`` then re-evaluates the
shipped weights on the slice and compares with the card.
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FIXTURE_DIR = REPO / "tests" / "core" / "fixtures" / "ndn"
SLICE = FIXTURE_DIR / "heldout_slice.npz"
SLICE_SCORES = FIXTURE_DIR / "heldout_slice_scores.json"
CARD = REPO / "docs" / "ndn_model_card.md"
# (held-out shard, view) of the slice: the preset training never saw, a training preset's
# new seed, and a rover-height view
SLICE_PICKS = (("heldout_layered_outcrop_100005", 2), ("heldout_dune_field_100002", 5),
               ("heldout_rocky_slope_100003", 1))
# how a run used its data, when that is not the plain story (e.g. the 2026-11-22 affine run was
# started on 44 scenes and resumed on 75); empty by default
DEFAULT_NOTE = ""
METRICS = ("abs_rel", "delta1", "normal_mean_deg", "normal_within_11_25")
LABELS = {"abs_rel": "AbsRel", "delta1": "delta1", "normal_mean_deg": "normal mean error (deg)",
          "normal_within_11_25": "< 11.25 deg"}


def fmt(key: str, value: float) -> str:
    """How the card and the slice test print a score (the test matches these strings)."""
    if key == "normal_mean_deg":
        return f"{value:.2f}"
    if key == "normal_within_11_25":
        return f"{100 * value:.1f} %"
    return f"{value:.4f}"


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def data_plan(data_dir: Path) -> dict:
    """What ``esgs ndn build-data`` made in ``data_dir``, read from its manifest: training and
    held-out-only presets, scene counts per split, views, resolution and samples."""
    manifest = json.loads((data_dir / "manifest.json").read_text())
    scenes = manifest.get("scenes", [])
    presets = list(dict.fromkeys(s["preset"] for s in scenes if s["split"] == "train"))
    heldout_only = [p for p in dict.fromkeys(s["preset"] for s in scenes if s["split"] == "heldout") if p not in presets]
    count = {split: sum(1 for s in scenes if s["split"] == split) for split in ("train", "validation", "heldout")}
    width, height = manifest.get("resolution", [160, 90])
    return {"presets": presets, "heldout_presets": heldout_only, "count": count, "views": manifest.get("views", 8),
            "width": width, "height": height, "samples": manifest.get("samples", 8),
            "working_size": manifest.get("working_size", 128),
            "palette": manifest.get("palette", "mars")}  # (a folder from before palettes holds the mars look)


def build_data_command(data_dir: Path, plan: dict) -> str:
    count = plan["count"]
    command = (f"esgs ndn build-data --out {data_dir} --scenes {count['train']} --heldout {count['heldout']} "
               f"--validation {count['validation']} --presets {' '.join(plan['presets'])}")
    if plan["heldout_presets"]:
        command += f" --heldout-presets {' '.join(plan['heldout_presets'])}"
    return command + (f" --views {plan['views']} --resolution {plan['width']}x{plan['height']} "
                      f"--samples {plan['samples']} --working-size {plan['working_size']} "
                      f"--palette {plan['palette']}")


def output_line(diffusion: dict, model: dict | None = None) -> str:
    """How to read the shipped depth output, by the weights' depth state (and evidence inputs)."""
    model = model or {}
    if model.get("evidence"):
        return ("- Output: depth in metres about each view's evidence (the scene's SfM points and, where "
                "`priors/labels` exists, its stereo labels: `reference x exp("
                f"{diffusion.get('log_depth_range', 2.5)} x state)` with the evidence's median as reference; relative "
                "for a view without evidence), unit camera-frame normals (OpenCV axes)"
                + (" and a sky probability (above one half: no surface, written as the priors' sky)" if model.get("sky")
                   else "") + " at 128 px on the long side, guided-upsampled to the image size. Held-out scores below "
                "read the shards' triangulated SfM points; the test slice is scored without evidence.")
    if diffusion.get("depth_state", "affine") == "log":
        return (f"- Output: relative depth in the log depth state (`exp({diffusion.get('log_depth_range', 2.5)} x state)`: "
                "true z depth up to one scale; `fit_scale_shift` recovers it with a shift of ~0) and unit "
                "camera-frame normals (OpenCV axes) at 128 px on the long side, guided-upsampled to the image size.")
    return ("- Output: relative depth (affine in true z depth; align with `fit_scale_shift`) and unit "
            "camera-frame normals (OpenCV axes) at 128 px on the long side, guided-upsampled to the image size.")


def evaluate_split(model, diffusion, data_dir: Path, split: str) -> dict:
    """Every triple of a split scored as ``esgs ndn eval`` scores it (triple i from seed i), with
    the means overall and per scene (shard)."""
    from esgs.core.ndn.data import load_shards
    from esgs.core.ndn.infer import evaluate_arrays, mean_scores, scores_by_scene

    arrays = load_shards(data_dir, split, with_scenes=True)
    scenes = arrays.pop("scene")
    evidence = "sfm" if model.config.evidence and "sfm_depth" in arrays else "none"
    per_view = evaluate_arrays(model, diffusion, arrays, seed=0, evidence_mode=evidence)
    return {"triples": len(per_view), **mean_scores(per_view), "per_scene": scores_by_scene(per_view, scenes)}


def cut_slice(data_dir: Path) -> None:
    """Write the slice's arrays once (later ships keep them, so the test data never moves)."""
    from esgs.core.io_utils import atomic_path

    parts: dict[str, list] = {"views": [], "depth": [], "normal": [], "mask": [], "names": []}
    for shard, view in SLICE_PICKS:
        with np.load(data_dir / "shards" / f"{shard}.npz", allow_pickle=False) as arrays:
            for key in ("views", "depth", "normal", "mask"):
                parts[key].append(arrays[key][view])
            parts["names"].append(f"{shard}/{arrays['names'][view]}")
    FIXTURE_DIR.mkdir(parents=True, exist_ok=True)
    with atomic_path(SLICE) as tmp:
        with open(tmp, "wb") as handle:
            np.savez_compressed(handle, **{key: np.stack(value) for key, value in parts.items()})


def _stage_facts(checkpoint: Path, step: int) -> dict:
    """One training run's facts up to ``step``: wall time from its events, CPU time and the
    validation scores from the checkpoint, its config and where it started from."""
    model_dir = checkpoint.parent.parent
    facts: dict = {"model_dir": str(model_dir), "to_step": step}
    events = model_dir / "events.jsonl"
    if events.exists():
        times = {}
        for line in events.read_text().splitlines():
            try:
                event = json.loads(line)
            except json.JSONDecodeError:
                continue
            if event.get("stage") == "ndn-train" and event.get("kind") == "progress":
                times.setdefault(int(event["step"]), float(event["time"]))
        first = min(times) if times else None
        if first is not None and step in times:
            facts["from_step"] = first - 1
            facts["train_seconds"] = round(times[step] - times[first], 1)
            facts["started"] = datetime.datetime.fromtimestamp(times[first], datetime.timezone.utc).strftime(
                "%Y-%m-%d %H:%M UTC")
    config = model_dir / "config.json"
    if config.exists():
        facts["config"] = json.loads(config.read_text())
    summary = model_dir / "train_summary.json"
    if summary.exists():
        facts["train_triples"] = json.loads(summary.read_text()).get("train_triples")
    if checkpoint.exists():
        import torch

        payload = torch.load(checkpoint, map_location="cpu", weights_only=True)
        for key in ("cpu_seconds", "validation", "lineage"):
            if key in payload:
                facts[key] = payload[key]
        if "provenance" in payload:
            # an exported weights file (e.g. weights shipped before, fine-tuned with --init): its own
            # run folders may be gone, so it is one stage described by what export_weights recorded
            provenance = payload["provenance"]
            if int(provenance.get("step", payload.get("step", -1))) != step:
                # the file was replaced since the fine-tune started from it (shipping overwrites the
                # shipped weights): its facts are another model's
                provenance = {"source": f"step {step}, since replaced at that path"}
            facts.update(exported=str(checkpoint), exported_provenance=provenance)
            if provenance.get("train_seconds"):
                facts["train_seconds"] = float(provenance["train_seconds"])
    return facts


def training_facts(checkpoint: Path, step: int) -> dict:
    """The facts of the run that wrote ``checkpoint`` and, for a fine-tune (``--init``), of the
    runs it started from: ``stages`` lists them oldest first; ``train_seconds`` sums their wall time."""
    stages = [_stage_facts(checkpoint, step)]
    while "exported" not in stages[0] and (stages[0].get("lineage", {}).get("init_from")
                                           or stages[0].get("config", {}).get("init_from")):
        lineage = stages[0].get("lineage") or stages[0]["config"]
        stages.insert(0, _stage_facts(Path(lineage["init_from"]), int(lineage["init_step"])))
    facts = dict(stages[-1])
    facts["stages"] = stages
    if all("train_seconds" in stage for stage in stages):
        facts["train_seconds"] = round(sum(stage["train_seconds"] for stage in stages), 1)
    facts["started"] = stages[0].get("started")
    return facts


def _schedule(train: dict) -> str:
    if train.get("lr_schedule", "constant") == "constant":
        return f"constant lr {train.get('learning_rate')}"
    warmup = f", {train['warmup_steps']} warm-up steps" if train.get("warmup_steps") else ""
    return (f"{train['lr_schedule']} lr {train.get('learning_rate')} -> {train.get('min_lr_ratio')} x that{warmup}")


def stage_lines(facts: dict) -> list[str]:
    """One bullet per training run behind the shipped weights."""
    lines = []
    for stage in facts["stages"]:
        if "exported" in stage:
            provenance = stage["exported_provenance"]
            text = (f"- Steps 0 -> {stage['to_step']}: the exported weights `{stage['exported']}` (from "
                    f"`{provenance.get('source', '?')}` of a run on `{provenance.get('data', '?')}`"
                    + (f", {provenance['train_triples']} training triples" if provenance.get("train_triples") else "")
                    + ")")
            if stage.get("train_seconds"):
                text += f"; wall time of the runs behind them {stage['train_seconds'] / 3600:.2f} h"
            cpu = provenance.get("cpu_seconds")
            if cpu:
                text += (f"; CPU time of their last run {cpu['train'] / 3600:.2f} h training + "
                         f"{cpu['validation'] / 3600:.2f} h validation scoring")
            lines.append(text + "; how they were trained: the model card in the git history of the commit that "
                         "shipped them.")
            continue
        train = stage.get("config", {}).get("train", {})
        ema = train.get("ema_decay", 0.0)
        start = stage.get("lineage", {}).get("init_step", stage.get("from_step", 0)) or 0
        cpu = stage.get("cpu_seconds")
        text = (f"- Steps {start} -> {stage['to_step']} (`{stage['model_dir']}`): AdamW, {_schedule(train)}, "
                f"batch {train.get('batch_size')}, seed {train.get('seed')}, {train.get('threads')} torch thread(s), "
                "horizontal flips" + (f", EMA of the weights (decay {ema}, the average is what ships)" if ema else
                                      ", no weight average"))
        if stage.get("train_seconds"):
            text += f"; wall time {stage['train_seconds'] / 3600:.2f} h"
        if stage.get("started"):
            text += f" (started {stage['started']})"
        if cpu:
            text += (f"; CPU time {cpu['train'] / 3600:.2f} h training + {cpu['validation'] / 3600:.2f} h "
                     "validation scoring")
        lines.append(text + ".")
    return lines


def card(step: int, facts: dict, weights: Path, heldout: dict, landform: dict | None, slice_scores: dict,
         baselines: dict, data_dir: Path, landform_dir: Path, seconds: float, note: str,
         validation: dict | None = None, extra: dict | None = None) -> str:
    config = facts.get("config", {})
    ndn = config.get("ndn", {})
    hours = facts.get("train_seconds")
    shipped_diffusion = torch_config(weights)
    plan = data_plan(data_dir)
    trained_scenes = len(list((data_dir / "shards").glob("train_*.npz")))
    training_presets = ", ".join(plan["presets"][:-1]) + (" and " if len(plan["presets"]) > 1 else "") + plan["presets"][-1]
    last_model = "MODEL" if len(facts["stages"]) == 1 else f"MODEL_FT{len(facts['stages']) - 1}"  # as in the commands
    sampling_text = (f"DDIM {shipped_diffusion['sample_steps']} steps"
                     + (f", median of {shipped_diffusion['sample_ensemble']} samples"
                        if shipped_diffusion.get("sample_ensemble", 1) > 1 and
                        shipped_diffusion.get("sample_reduce") == "median" else
                        f", mean of {shipped_diffusion.get('sample_ensemble')} samples"
                        if shipped_diffusion.get("sample_ensemble", 1) > 1 else ""))
    row = lambda label, s: (f"| {label} | {s['triples']} | " + " | ".join(fmt(k, s[k]) for k in METRICS) + " |")  # noqa: E731
    header = ["| method | triples | AbsRel | delta1 | normal mean error (deg) | < 11.25 deg |", "|---|---|---|---|---|---|"]
    lines = [
        "# NDN model card (the weights shipped in `core/ndn/weights/ndn_mars.pt`)",
        "",
        "Generated by `benchmarks/ship_ndn.py`; do not edit by hand (re-run it instead).",
        "",
        "In the product these weights write the **depth** and the surface mask of `priors/ndn`; the normals and the sky come from the completion network shipped beside them (docs/ndn_completion_model_card.md).",
        "",
        "## Model",
        f"- Network: the two-branch NDN UNet of docs/ndn.md, {ndn.get('model', {})}; diffusion as shipped "
        f"{shipped_diffusion}.",
        f"- Weights: {weights.stat().st_size / 1e6:.1f} MB, float16 (loaded as float32), sha256 `{sha256(weights)[:16]}`, "
        f"training step **{step}**.",
        output_line(shipped_diffusion, ndn.get("model", {})),
        "",
        "## Training",
        f"- Data: `{data_dir}` from `esgs ndn build-data` (command below): synthetic Mars scenes of the presets "
        f"{training_presets}, {plan['views']} views each at {plan['width']}x{plan['height']} (Cycles, "
        f"{plan['samples']} samples), one triple per view at the working size; held-out scenes use seeds >= 100000"
        + (f" and add {', '.join(plan['heldout_presets'])}, which training never saw" if plan["heldout_presets"] else "")
        + "." + f" Training scenes in the data folder now: {trained_scenes} ({plan['views'] * trained_scenes} triples)."
        + (f" {note}" if note else ""),
        *stage_lines(facts),
        f"- Steps: {step}" + (f"; wall time to this step {hours / 3600:.2f} h" if hours else "")
        + (f" (first run started {facts['started']})" if facts.get("started") else "")
        + " on the shared 2-core CPU machine, under heavy load from other jobs.",
        "",
        f"## Held-out scores (these weights, {sampling_text}, seed 0 + triple index)",
        "",
        *header, row("NDN (shipped)", heldout),
        "",
        "Per held-out scene:",
        "",
        "| scene | " + " | ".join(LABELS[k] for k in METRICS) + " |", "|---|---|---|---|---|",
        *[f"| {scene} | " + " | ".join(fmt(k, s[k]) for k in METRICS) + " |"
          for scene, s in heldout["per_scene"].items()],
    ]
    if validation:
        lines += ["", f"Validation split (`{data_dir}` shards `validation_*`: training presets, seeds >= 50000, "
                  "never trained on nor held out; the step to ship is chosen on it, see docs/ndn.md):", "",
                  *header, row("NDN (shipped)", validation)]
        picked = facts.get("validation")
        record = Path(facts["model_dir"]) / "validation.json"
        if picked and record.exists():
            best = json.loads(record.read_text())["best"]
            lines += ["", f"Validation score of this checkpoint at training time: {picked['score']:.3f} over "
                      f"{picked['triples']} triples (AbsRel / 0.065 + (1 - delta1) / 0.027 + normal error / 20 deg, "
                      f"EMA weights, DDIM {picked.get('ddim_steps', '?')} steps x {picked.get('ensemble', 1)} "
                      f"samples ({picked.get('reduce', 'median')}); lower is better); the "
                      f"run's best checkpoint on it: step {best['step']} ({best['score']:.3f}). Every checkpoint's "
                      f"score: `{record}`."]
    if landform:
        lines += ["", f"Real-mesh views (`{landform_dir}`, mars_landform rendered, never used in training):", "",
                  *header, row("NDN (shipped)", landform)]
    for name, (folder, scores) in (extra or {}).items():
        lines += ["", f"{name} (`{folder}`, held-out shards, never used in training):", "",
                  *header, row("NDN (shipped)", scores)]
    if baselines:
        lines += ["", "## Baselines (from `benchmarks/ndn_baselines.py`, measured separately; see docs/ndn.md)", ""]
        for key, methods in baselines.items():
            lines += [f"{key}:", "", *header]
            lines += [row(label, summary) for label, summary in methods.items()]
            lines.append("")
    lines += [
        "## Test slice",
        "",
        f"`tests/core/fixtures/ndn/heldout_slice.npz` ({len(slice_scores['names'])} held-out triples: "
        f"{', '.join(slice_scores['names'])}). `tests/core/ndn/test_shipped.py` re-evaluates the shipped weights on it "
        "and checks these scores (tolerance in the test):",
        "",
        "| slice | " + " | ".join(LABELS[k] for k in METRICS) + " |", "|---|---|---|---|---|",
        "| heldout_slice | " + " | ".join(fmt(k, slice_scores["scores"][k]) for k in METRICS) + " |",
        "",
        "## Reproduce",
        "",
        "```",
        build_data_command(data_dir, plan),
        *reproduce_train_lines(facts, data_dir),
        f".venv/bin/python benchmarks/ship_ndn.py {last_model}/checkpoints/step_{step:07d}.pt --data {data_dir}"
        + (f" --sample-steps {shipped_diffusion['sample_steps']}" if shipped_diffusion["sample_steps"] != 15 else "")
        + (f" --ensemble {shipped_diffusion['sample_ensemble']} --reduce {shipped_diffusion['sample_reduce']}"
           if shipped_diffusion.get("sample_ensemble", 1) > 1 else ""),
        f"esgs ndn eval core/ndn/weights/ndn_mars.pt {data_dir}",
        "# the real-mesh set (two orbits of the landform mesh), and its shards",
        *[f"esgs scene --mesh ../shared/data/mars_landform/terrain.glb --rig orbit --views 8 --resolution 160x90 "
          f"--samples 8 --seed {seed} --out {landform_dir}/scenes/heldout_orbit_s{seed}" for seed in (1, 2)],
        f"esgs ndn shard {landform_dir}/scenes/* --data {landform_dir}",
        "# the baselines (regression: the same network and data, --prediction regression)",
        f"esgs ndn train {data_dir} --out REGRESSION --steps N --batch-size 8 --checkpoint-every 100 --threads 1 "
        "--seed 0 --prediction regression",
        f".venv/bin/python benchmarks/ndn_baselines.py {data_dir} {landform_dir} --method sfm "
        "--method ndn:stepN=MODEL/checkpoints/step_N.pt --method regression:stepN=REGRESSION/checkpoints/step_N.pt "
        "--json benchmarks/results/ndn_baselines.json",
        "```",
        "",
        f"Shipping and scoring took {seconds:.0f} s. Limits: see docs/ndn.md (\"Limits\").",
        "",
    ]
    return "\n".join(lines)


def torch_config(weights: Path) -> dict:
    """The diffusion settings stored in a weights file (what inference uses)."""
    import torch

    return torch.load(weights, map_location="cpu", weights_only=True)["config"]["diffusion"]


def reproduce_train_lines(facts: dict, data_dir: Path) -> list[str]:
    """The `esgs ndn train` command of every run behind the weights."""
    lines = []
    init_path = None  # how the next run names its starting point, from its init step; None before the first run
    for index, stage in enumerate(facts["stages"]):
        if "exported" in stage:
            lines.append(f"# steps 0-{stage['to_step']}: the exported weights {stage['exported']} "
                         "(their own commands: the model card of the commit that shipped them)")
            init_path = lambda _step, path=stage["exported"]: path  # noqa: E731
            continue
        train = stage.get("config", {}).get("train", {})
        out = "MODEL" if index == 0 else f"MODEL_FT{index}"
        command = (f"esgs ndn train {data_dir} --out {out} --steps {train.get('steps', stage['to_step'])} --batch-size "
                   f"{train.get('batch_size', 8)} --checkpoint-every {train.get('checkpoint_every', 100)} --threads 1 "
                   f"--seed {train.get('seed', 0)}")
        if "lr_schedule" in train:
            command += (f" --learning-rate {train['learning_rate']} --lr-schedule {train['lr_schedule']} "
                        f"--min-lr-ratio {train['min_lr_ratio']} --warmup-steps {train['warmup_steps']} "
                        f"--ema-decay {train['ema_decay']} --validation-triples {train['validation_triples']}")
            for key in ("validation_steps", "validation_ensemble", "validation_reduce"):
                if train.get(key):
                    command += f" --{key.replace('_', '-')} {train[key]}"
        else:
            command += " --lr-schedule constant --ema-decay 0  # (run before schedules and EMA existed)"
        depth_state = stage.get("config", {}).get("ndn", {}).get("diffusion", {}).get("depth_state", "affine")
        if init_path is None and depth_state != "affine":
            command += f" --depth-state {depth_state}"  # a fine-tune keeps its checkpoint's state
        if init_path is not None:
            command += f" --init {init_path(stage.get('lineage', {}).get('init_step', 0))}"
        lines.append(command)
        init_path = lambda step, out=out: f"{out}/checkpoints/step_{step:07d}.pt"  # noqa: E731
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path, help="MODEL/checkpoints/step_<N>.pt (or weights.pt)")
    parser.add_argument("--data", type=Path, default=Path("/work/runs/ndn_data"), help="data folder (held-out shards)")
    parser.add_argument("--landform", type=Path, default=Path("/work/runs/ndn_landform"),
                        help="held-out landform data folder (skipped when absent)")
    parser.add_argument("--extra", action="append", default=[], metavar="NAME=DIR",
                        help="another held-out data folder to score and report (repeat), e.g. rover-like views")
    parser.add_argument("--baselines", type=Path, default=REPO / "benchmarks" / "results" / "ndn_baselines.json")
    parser.add_argument("--navcam", type=Path, default=Path("/work/runs/ndn_navcam/station"),
                        help="the registered Navcam station for docs/images (skipped when absent)")
    parser.add_argument("--note", default=DEFAULT_NOTE, help="how the run used the data (goes into the card)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--sample-steps", type=int, default=None, help="DDIM steps stored with the shipped weights")
    parser.add_argument("--ensemble", type=int, default=None, help="samples per view stored with the shipped weights")
    parser.add_argument("--reduce", choices=("median", "mean"), default=None, help="how the ensemble is combined")
    parser.add_argument("--card-only", action="store_true",
                        help="only rewrite the model card from the scores the last ship saved (e.g. after new "
                             "baseline figures); the checkpoint must be the one shipped")
    args = parser.parse_args()

    import torch

    from esgs.core.io_utils import atomic_write_json, atomic_write_text
    from esgs.core.ndn.infer import evaluate_arrays, mean_scores
    from esgs.core.ndn.shipped import SHIPPED_WEIGHTS, export_weights
    from esgs.core.ndn.train import load_checkpoint

    torch.set_num_threads(args.threads)
    started = time.time()
    _, _, _, payload = load_checkpoint(args.checkpoint)
    step = int(payload["step"])
    facts = training_facts(args.checkpoint, step)
    if args.card_only:
        return rewrite_card(args, step, facts, started)
    sampling = {key: value for key, value in (("sample_steps", args.sample_steps), ("sample_ensemble", args.ensemble),
                                              ("sample_reduce", args.reduce)) if value is not None}
    export_weights(args.checkpoint, SHIPPED_WEIGHTS, sampling=sampling, provenance={
        "source": args.checkpoint.name, "step": step, "data": str(args.data),
        "train_seconds": facts.get("train_seconds"), "train_triples": facts.get("train_triples"),
        "cpu_seconds": facts.get("cpu_seconds"), "lineage": facts.get("lineage")})
    model, diffusion, _, _ = load_checkpoint(SHIPPED_WEIGHTS)  # score what ships (float16 -> float32)
    print(f"wrote {SHIPPED_WEIGHTS} ({SHIPPED_WEIGHTS.stat().st_size / 1e6:.1f} MB, step {step})", flush=True)

    heldout = evaluate_split(model, diffusion, args.data, "heldout")
    print("held-out:", json.dumps({k: heldout[k] for k in ("triples", *METRICS)}), flush=True)
    validation = None
    if any((args.data / "shards").glob("validation_*.npz")):
        validation = evaluate_split(model, diffusion, args.data, "validation")
        print("validation:", json.dumps({k: validation[k] for k in ("triples", *METRICS)}), flush=True)
    landform = None
    if (args.landform / "shards").exists():
        landform = evaluate_split(model, diffusion, args.landform, "heldout")
        print("landform:", json.dumps({k: landform[k] for k in ("triples", *METRICS)}), flush=True)
    extra = {}
    for item in args.extra:
        name, _, folder = item.partition("=")
        scores = evaluate_split(model, diffusion, Path(folder), "heldout")
        extra[name] = (folder, scores)
        print(f"{name}:", json.dumps({k: scores[k] for k in ("triples", *METRICS)}), flush=True)

    if not SLICE.exists():
        cut_slice(args.data)
    with np.load(SLICE, allow_pickle=False) as arrays:
        slice_arrays = {key: arrays[key] for key in arrays.files}
    slice_scores = {"weights_sha256": sha256(SHIPPED_WEIGHTS), "step": step, "ddim_steps": diffusion.config.sample_steps,
                    "ensemble": diffusion.config.sample_ensemble, "seed": 0,
                    "names": [str(name) for name in slice_arrays["names"]],
                    "scores": mean_scores(evaluate_arrays(model, diffusion, slice_arrays, seed=0))}
    atomic_write_json(SLICE_SCORES, slice_scores)
    print("slice:", json.dumps(slice_scores["scores"]), flush=True)

    if (args.navcam / "sparse").exists():
        sys.path.insert(0, str(REPO / "benchmarks"))
        from ndn_navcam_figures import navcam_figures

        for path in navcam_figures(args.navcam, REPO / "docs" / "images", SHIPPED_WEIGHTS):
            print(f"wrote {path}", flush=True)
    baselines = json.loads(args.baselines.read_text()) if args.baselines.exists() else {}
    atomic_write_text(CARD, card(step, facts, SHIPPED_WEIGHTS, heldout, landform, slice_scores, baselines,
                                 args.data, args.landform, time.time() - started, args.note, validation, extra))
    atomic_write_json(REPO / "benchmarks" / "results" / "ndn_shipped_scores.json",
                      {"step": step, "heldout": heldout, "landform": landform, "validation": validation,
                       "extra": {name: {"folder": folder, "scores": scores} for name, (folder, scores) in extra.items()},
                       "seconds": round(time.time() - started, 1)})
    print(f"wrote {CARD} and {SLICE_SCORES} in {time.time() - started:.0f} s")
    return 0


def rewrite_card(args: argparse.Namespace, step: int, facts: dict, started: float) -> int:
    from esgs.core.io_utils import atomic_write_text
    from esgs.core.ndn.shipped import SHIPPED_WEIGHTS

    saved = json.loads((REPO / "benchmarks" / "results" / "ndn_shipped_scores.json").read_text())
    slice_scores = json.loads(SLICE_SCORES.read_text())
    if saved["step"] != step or slice_scores["weights_sha256"] != sha256(SHIPPED_WEIGHTS):
        sys.exit(f"the shipped weights are not step {step}'s scored ones: run without --card-only")
    baselines = json.loads(args.baselines.read_text()) if args.baselines.exists() else {}
    atomic_write_text(CARD, card(step, facts, SHIPPED_WEIGHTS, saved["heldout"], saved["landform"], slice_scores,
                                 baselines, args.data, args.landform, saved.get("seconds", 0.0), args.note,
                                 saved.get("validation"),
                                 {name: (item["folder"], item["scores"]) for name, item in saved.get("extra", {}).items()}))
    print(f"rewrote {CARD}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
