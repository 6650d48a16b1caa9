"""Where a completion network's depth wins or loses against today's fill: the pixels stereo leaves empty.

On the views with sky of each scene (the rover-height ones), the surface pixels without a stereo
label are the holes the network fills inside ``priors/auto``. There the metric relative error
``|d - truth| / truth`` (no alignment: both fills are in the scene's metres) of

- ``network``: the network's output with the SfM points and stereo labels as evidence;
- ``old_fill``: what ``benchmarks/ndn_completion.py`` calls ``stereo_filled`` (the shipped NDN
  pinned to the SfM points inside ``auto``, SfM interpolation where ``auto`` has nothing);

split by true range (near / middle / far) and by the network's own sky call, plus a check of
the log state's span about the evidence reference (``reference x/÷ e^log_depth_range``): the
share of surface pixels nearer than it can represent. Uses the same scene preparation and cache
as ``ndn_completion.py`` (``--work``).

    .venv/bin/python benchmarks/ndn_hole_errors.py --weights MODEL/checkpoints/step_N.pt \\
        --work /work/runs/c25/s8/evalwork --json OUT.json SCENE [SCENE ...]
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # an idle OpenMP worker must not spin beside other jobs

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ndn_completion  # noqa: E402

RANGES_M = ((0.0, 30.0), (30.0, 100.0), (100.0, math.inf))


def _summary(errors: list[np.ndarray]) -> dict:
    values = np.concatenate(errors) if errors else np.zeros(0)
    if not values.size:
        return {"pixels": 0}
    return {"pixels": int(values.size), "mean": float(values.mean()), "median": float(np.median(values))}


def hole_errors(weights: Path, scenes: list[Path], work: Path) -> dict:
    """The split errors over the views with sky of ``scenes`` (module docstring)."""
    from esgs.core.ndn.checkpoint import load_checkpoint
    from esgs.core.ndn.infer import predict_triple

    model, diffusion, config, _ = load_checkpoint(weights)
    if not config.model.evidence:
        raise SystemExit(f"{weights}: these weights read no evidence; the holes of the fused prior need a network that does")
    log_range = config.diffusion.log_depth_range
    buckets: dict[str, dict[str, list[np.ndarray]]] = {}
    views, hole_share, sky_called, below_span = 0, [], [], []

    def add(bucket: str, source: str, values: np.ndarray) -> None:
        buckets.setdefault(bucket, {}).setdefault(source, []).append(values)

    for scene in scenes:
        copy = ndn_completion.prepare_scene(scene, work)
        data = ndn_completion.scene_views(scene, copy)
        for index in range(len(data["names"])):
            truth, mask = data["depth"][index], data["mask"][index]
            if float((~mask).mean()) < ndn_completion.SKY_VIEW_SHARE:
                continue
            views += 1
            depth, _, sky, _ = predict_triple(model, diffusion, data, index, seed=index, evidence_mode="sfm_stereo")
            sky = np.zeros_like(truth) if sky is None else np.asarray(sky).reshape(truth.shape)
            stereo = data["stereo_depth"][index]
            dense, _ = ndn_completion._interpolated(data["sfm_depth"][index], data["intrinsics"])
            old = ndn_completion.stereo_filled_depth(data, index, dense)
            surface = mask & (truth > 0)
            holes = surface & (stereo <= 0)
            hole_share.append(float(holes.sum() / max(surface.sum(), 1)))
            sky_called.append(float((surface & (sky > 0.5)).sum() / max(surface.sum(), 1)))
            evidence = np.concatenate([stereo[stereo > 0], data["sfm_depth"][index][data["sfm_depth"][index] > 0]])
            if evidence.size:
                nearest = float(np.median(evidence)) / math.exp(log_range)
                below_span.append(float((truth[surface] < nearest).mean()))
            for source, fill in (("network", np.asarray(depth)), ("old_fill", old)):
                error = np.abs(fill - truth)[holes] / truth[holes]
                add("holes", source, error)
                add("holes, network calls sky", source, error[sky[holes] > 0.5])
                add("holes, network calls surface", source, error[sky[holes] <= 0.5])
                for low, high in RANGES_M:
                    inside = (truth[holes] >= low) & (truth[holes] < high)
                    add(f"holes, true range {low:g}-{high:g} m", source, error[inside])
    return {"views_with_sky": views, "hole_share_of_surface": float(np.mean(hole_share)) if hole_share else 0.0,
            "surface_called_sky": float(np.mean(sky_called)) if sky_called else 0.0,
            "surface_nearer_than_the_log_span": float(np.mean(below_span)) if below_span else 0.0,
            "relative_error": {bucket: {source: _summary(parts) for source, parts in sources.items()}
                               for bucket, sources in buckets.items()}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", type=Path, nargs="+", help="scene folders (rendered, with priors/gt)")
    parser.add_argument("--weights", type=Path, required=True, help="evidence-reading network weights")
    parser.add_argument("--work", type=Path, required=True, help="cache of prepared scene copies (as ndn_completion.py)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    result = {"what": "metric relative error in the stereo holes of views with sky: completion network vs today's fill "
                      "(benchmarks/ndn_hole_errors.py)",
              "command": "python " + " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]),
              "weights": str(args.weights), "scenes": [str(s) for s in args.scenes],
              **hole_errors(args.weights, args.scenes, args.work)}
    from esgs.core.io_utils import atomic_write_json

    atomic_write_json(args.json, result)
    for bucket, sources in result["relative_error"].items():
        line = "  ".join(f"{source} {s.get('mean', float('nan')):.3f}/{s.get('median', float('nan')):.3f}"
                         for source, s in sources.items())
        print(f"{bucket:32s} pixels {sources['network']['pixels']:6d}  {line}")
    print(f"holes {100 * result['hole_share_of_surface']:.1f} % of surface; surface called sky "
          f"{100 * result['surface_called_sky']:.2f} %; surface nearer than the log span "
          f"{100 * result['surface_nearer_than_the_log_span']:.2f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
