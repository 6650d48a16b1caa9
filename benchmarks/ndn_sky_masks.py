"""The sky masks `esgs priors --method ndn` writes, scored against a reference: real Navcam frames or a rendered scene.

The frames of ``../shared/data/mars_navcam_pan`` come without sky masks, so this script draws
rough ones by a rule (:func:`rough_sky`): pixels that are bright and flat (Gaussian-blurred
grey above 140, gradient magnitude below 10) and connected to the frame's top (row 10: the
frames have a dark border of a few rows). The rule misses thin slivers of sky and some skies
near the sun, and can take in flat bright haze at the horizon, so it is a reference to check
by eye (``--overlay`` draws it in red on every frame), not ground truth.

With ``--reference gt`` the reference is instead a scene's exact sky (where ``priors/gt`` has
no surface), for rendered scenes.

Each set of weights is run as ``esgs priors --method ndn`` runs it (``predict_sky_masks``: the
station's own evidence, none for a rotation-only station; the probability upsampled with the
image as guide and thresholded at one half). Per weights the JSON gives the pooled
precision / recall / IoU over all frames, the mean IoU over frames whose reference has at least
2 % sky, the share of sky marked on frames whose reference has none, and per frame figures.

    esgs dataset rotation-only ../shared/data/mars_navcam_pan/images --out STATION --focal-px 621
    .venv/bin/python benchmarks/ndn_sky_masks.py STATION --weights shipped=core/ndn/weights/ndn_completion.pt \\
        candidate=PATH --out benchmarks/results/ndn_sky_masks_navcam_DATE.json --overlay docs/images/navcam_sky_reference.png
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
TOP_ROW = 10  # below the frames' dark border
SKY_FRAME_MIN = 0.02  # frames with at least this share of reference sky count as "with sky"


def rough_sky(grey: np.ndarray, bright: float = 140.0, flat: float = 10.0) -> np.ndarray:
    """Bright, flat pixels connected to the top of an 8-bit grey frame [H, W] -> bool [H, W]."""
    import cv2

    blurred = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 2)
    gradient = np.hypot(cv2.Sobel(blurred, cv2.CV_32F, 1, 0), cv2.Sobel(blurred, cv2.CV_32F, 0, 1))
    candidate = ((blurred > bright) & (gradient < flat)).astype(np.uint8)
    candidate = cv2.morphologyEx(candidate, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    _, labels = cv2.connectedComponents(candidate)
    touching = sorted(set(np.unique(labels[TOP_ROW]).tolist()) - {0})
    sky = np.isin(labels, touching).astype(np.uint8)
    return cv2.morphologyEx(sky, cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8)).astype(bool)


def predicted_sky(scene: Path, weights: Path) -> dict[str, np.ndarray]:
    """Each frame's sky mask as ``esgs priors --method ndn`` writes it (full image size)."""
    from esgs.core.errors import ConfigError
    from esgs.core.ndn.infer import predict_sky_masks

    try:
        return predict_sky_masks(scene, weights)
    except ConfigError as error:
        raise SystemExit(str(error)) from error


def score(reference: dict[str, np.ndarray], predicted: dict[str, np.ndarray]) -> dict:
    """Pooled and per-frame agreement of ``predicted`` with ``reference`` (same frame names)."""
    names = sorted(reference)
    hit = sum(int((reference[n] & predicted[n]).sum()) for n in names)
    marked = sum(int(predicted[n].sum()) for n in names)
    truth = sum(int(reference[n].sum()) for n in names)
    union = sum(int((reference[n] | predicted[n]).sum()) for n in names)
    per_frame = {}
    for name in names:
        ref, pred = reference[name], predicted[name]
        union_frame = int((ref | pred).sum())
        per_frame[name] = {"reference_sky": round(float(ref.mean()), 4), "marked_sky": round(float(pred.mean()), 4),
                           "iou": round(float((ref & pred).sum() / union_frame), 4) if union_frame else None}
    with_sky = [n for n in names if reference[n].mean() >= SKY_FRAME_MIN]
    without = [n for n in names if not reference[n].any()]
    return {
        "precision": round(hit / marked, 4) if marked else None,
        "recall": round(hit / truth, 4) if truth else None,
        "iou": round(hit / union, 4) if union else None,
        "mean_iou_frames_with_sky": round(float(np.mean([per_frame[n]["iou"] for n in with_sky])), 4),
        "frames_with_sky": len(with_sky),
        "frames_with_any_sky_marked": sum(bool(predicted[n].any()) for n in with_sky),
        "marked_on_frames_without_sky": round(float(np.mean([predicted[n].mean() for n in without])), 4)
        if without else None,
        "frames_without_sky": len(without),
        "per_frame": per_frame,
    }


def draw_overlay(scene: Path, reference: dict[str, np.ndarray], path: Path, tile: int = 128) -> None:
    """Every frame, small, with its reference sky tinted red: for checking the rule by eye."""
    import cv2

    from esgs.core.formats.imageio import read_image, write_png
    from esgs.core.formats.scene_dir import SceneDir

    tiles = []
    for name in sorted(reference):
        grey = read_image(SceneDir(scene).image(name))
        grey = grey if grey.ndim == 2 else grey[..., 0]
        small = cv2.resize(grey, (tile, tile), interpolation=cv2.INTER_AREA)
        rgb = np.repeat(small[..., None], 3, axis=-1).astype(np.float32)
        sky = cv2.resize(reference[name].astype(np.uint8), (tile, tile), interpolation=cv2.INTER_NEAREST) > 0
        rgb[sky] = 0.5 * rgb[sky] + np.array([127.0, 0.0, 0.0])
        tiles.append(rgb.astype(np.uint8))
    while len(tiles) % 8:
        tiles.append(np.zeros_like(tiles[0]))
    write_png(path, np.concatenate([np.concatenate(tiles[i:i + 8], axis=1) for i in range(0, len(tiles), 8)]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path, help="the registered Navcam station (esgs dataset rotation-only)")
    parser.add_argument("--weights", nargs="+", required=True, metavar="LABEL=PATH")
    parser.add_argument("--out", type=Path, required=True, help="JSON file to write")
    parser.add_argument("--overlay", type=Path, default=None, help="PNG of the reference masks")
    parser.add_argument("--reference", choices=("rule", "gt"), default="rule",
                        help="rule: bright, flat and connected to the top (real frames); gt: no surface in priors/gt")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()

    import torch

    from esgs.core.formats.imageio import read_image
    from esgs.core.formats.scene_dir import SceneDir
    from esgs.core.io_utils import atomic_write_json

    torch.set_num_threads(args.threads)
    scene = SceneDir(args.scene)
    reference = {}
    for path in sorted(p for p in scene.images.iterdir() if p.is_file()):
        if args.reference == "gt":
            from esgs.core.priors import load_prior_maps

            reference[path.name] = ~load_prior_maps(args.scene, "gt", path.name).mask
            continue
        grey = read_image(scene.image(path.name))
        reference[path.name] = rough_sky(grey if grey.ndim == 2 else grey[..., 0])
    if args.overlay:
        draw_overlay(args.scene, reference, args.overlay)
    results = {}
    for entry in args.weights:
        label, _, weights = entry.partition("=")
        start = time.perf_counter()
        predicted = predicted_sky(args.scene, Path(weights))
        results[label] = {"weights": weights, "sha256": hashlib.sha256(Path(weights).read_bytes()).hexdigest()[:16],
                          "seconds": round(time.perf_counter() - start, 1),
                          **score({n: reference[n] for n in predicted}, predicted)}
        summary = {k: v for k, v in results[label].items() if k != "per_frame"}
        print(label, json.dumps(summary))
    atomic_write_json(args.out, {
        "what": __doc__.splitlines()[0],
        "date": datetime.date.today().isoformat(),
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "station": str(args.scene),
        "reference": {"rule": "rough_sky: blurred grey > 140, gradient < 10, connected to row 10"
                      if args.reference == "rule" else "exact: no surface in priors/gt", "frames": len(reference)},
        "results": results,
    })
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
