"""Rendered depth and normals of finished runs against a synthetic scene's exact maps.

The bench and the studies measure geometry as the distance of the opaque Gaussian centres
to the true mesh. That says nothing about the surface's orientation, which the normal prior
is for (slopes matter to a planetary scientist). This script renders every held-out view of
each run with its depth and composited normals and scores them against ``priors/gt`` as the
demo's report scores one view (``core.apps.report.geometry_scores``: depth AbsRel and delta1
after a robust scale/shift fit, mean normal angle and the share under 11.25 degrees), over
the pixels the run covers (alpha > 0.5) that the truth marks as surface.

    python benchmarks/rendered_geometry.py OUT [OUT ...] --json RESULT.json

OUT: folders written by ``benchmarks/device_study.py run`` (their ``rows.json`` names each
run ``work/runNNN``), or ``GROUP/ARM=FOLDER`` for a folder of run folders named by seed
(``sky_study.py``'s ``OUT/SCENE/ARM/seedS``) or a single run. The JSON holds one row per run
and the mean and spread per group and arm.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Any


KEYS = ("abs_rel", "delta1", "normal_mean_deg", "normal_within_11_25")


def run_scores(run_dir: Path, scene: Path) -> dict[str, float]:
    """Pixel-weighted scores of one run over its held-out views (see the module docstring)."""
    from esgs.core.apps.report import geometry_scores
    from esgs.core.methods import run_renderer
    from esgs.core.priors.io import load_prior_maps

    renderer = run_renderer(run_dir)
    totals: dict[str, float] = {key: 0.0 for key in KEYS}
    pixels = 0
    for view in renderer.views("test"):
        out = renderer.render(view, depth=True, normals=True)
        rotation = view.viewmat[:3, :3].double().numpy()
        truth = load_prior_maps(scene, "gt", view.name, size=(view.width, view.height),
                                world_to_camera_rotation=rotation)
        scores = geometry_scores(out.depth[..., 0].cpu().numpy(), out.normals.cpu().numpy(),
                                 out.alpha[..., 0].cpu().numpy() > 0.5, truth.depth, truth.normal,
                                 truth.mask.astype(bool))
        count = int(scores.get("pixels", 0))
        if not count or not all(key in scores for key in KEYS):
            continue
        pixels += count
        for key in KEYS:
            totals[key] += scores[key] * count
    return {key: totals[key] / pixels for key in KEYS} | {"pixels": pixels} if pixels else {"pixels": 0}


def _config(run_dir: Path) -> dict[str, Any]:
    """A run folder's saved settings as a dict ({} when it is not a run)."""
    from esgs.core.formats.run_dir import RunDir

    path = RunDir(run_dir).config
    return json.loads(path.read_text()) if path.is_file() else {}


def _runs(out: str) -> list[tuple[dict[str, Any], Path]]:
    """(row identity, run folder) of every run an OUT argument names (module docstring)."""
    if "=" in out:
        label, folder = out.split("=", 1)
        group, arm = label.rsplit("/", 1)
        folder = Path(folder)
        if _config(folder):
            return [({"name": label, "group": group, "arm": arm, "seed": None}, folder)]
        runs = []
        for run_dir in sorted(path for path in folder.iterdir() if path.is_dir() and _config(path)):
            seed = _config(run_dir).get("seed")
            runs.append(({"name": f"{label}/seed{seed}", "group": group, "arm": arm, "seed": seed}, run_dir))
        return runs
    rows = json.loads((Path(out) / "rows.json").read_text())["rows"]
    return [({key: row.get(key) for key in ("name", "group", "arm", "seed")},
             Path(out) / "work" / f"run{row['index']:03d}") for row in rows]


def measure(outs: list[str]) -> dict[str, Any]:
    rows = []
    for out in outs:
        for identity, run_dir in _runs(out):
            scores = run_scores(run_dir, Path(_config(run_dir)["scene"]))
            rows.append(identity | scores)
            print(f"{identity['name']}: " + ", ".join(f"{k} {scores[k]:.4g}" for k in KEYS if k in scores), flush=True)
    summary: dict[str, Any] = {}
    for row in rows:
        summary.setdefault(f"{row['group']}/{row['arm']}", []).append(row)
    for name, members in summary.items():
        summary[name] = {key: {"mean": statistics.fmean(m[key] for m in members if key in m),
                               "std": statistics.pstdev([m[key] for m in members if key in m]),
                               "n": sum(key in m for m in members)} for key in KEYS}
    return {"rows": rows, "summary": summary}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("outs", nargs="+", help="device_study OUT folders, or GROUP/ARM=FOLDER")
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args(argv)
    from esgs.core.io_utils import atomic_write_json

    result = measure(args.outs)
    result["command"] = "benchmarks/rendered_geometry.py " + " ".join(str(o) for o in args.outs)
    atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
