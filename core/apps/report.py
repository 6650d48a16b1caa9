"""The demo's report: one Markdown file with pictures beside it (``OUT/report.md``).

Pictures are composed with OpenCV: held-out renders beside the ground truth with magnified
crops, one view during training, priors against rendered depth and normals; the loss and PSNR
curves and the Blender heat map's colour bar are drawn with matplotlib when it is installed
(:mod:`.plots`, an optional dependency; plain OpenCV drawings otherwise).
"""
from __future__ import annotations

import json
import platform
import time
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np

from ..formats.imageio import read_image, write_png
from ..io_utils import atomic_write_text
from ..formats.scene_dir import PriorSource, SceneDir
from ..formats.run_dir import RunDir
from .drawing import _hstack, _rgb, plot_curves  # noqa: F401 - plot_curves is the report's API too

_WHITE = (255, 255, 255)


def _label(image: np.ndarray, text: str) -> np.ndarray:
    """Image with a caption strip on top."""
    strip = np.zeros((18, image.shape[1], 3), np.uint8)
    cv2.putText(strip, text, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, _WHITE, 1, cv2.LINE_AA)
    return np.concatenate([strip, _rgb(image)], axis=0)


def _vstack(images: list[np.ndarray], gap: int = 4) -> np.ndarray:
    width = max(i.shape[1] for i in images)
    padded = []
    for image in images:
        pad = np.zeros((image.shape[0] + gap, width, 3), np.uint8)
        pad[: image.shape[0], : image.shape[1]] = _rgb(image)
        padded.append(pad)
    return np.concatenate(padded, axis=0)[:-gap]


def magnified_crop(image: np.ndarray, box: tuple[int, int, int, int], scale: int = 3) -> np.ndarray:
    """``box`` = (x, y, w, h) cut out and enlarged ``scale`` times with nearest pixels."""
    x, y, w, h = box
    crop = _rgb(image)[y:y + h, x:x + w]
    return cv2.resize(crop, (w * scale, h * scale), interpolation=cv2.INTER_NEAREST)


def colorize_depth(depth: np.ndarray, valid: Optional[np.ndarray] = None, limits: Optional[tuple[float, float]] = None) -> np.ndarray:
    """Depth [H,W] as a turbo-coloured RGB image (black where invalid), near = red."""
    valid = (depth > 0) if valid is None else valid & (depth > 0)
    if not np.any(valid):
        return np.zeros((*depth.shape, 3), np.uint8)
    low, high = limits or (float(np.percentile(depth[valid], 2)), float(np.percentile(depth[valid], 98)))
    scaled = np.clip((high - depth) / max(high - low, 1e-9), 0, 1)
    colour = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    return np.where(valid[..., None], colour, 0).astype(np.uint8)


def colorize_normals(normals: np.ndarray, valid: Optional[np.ndarray] = None) -> np.ndarray:
    """Unit normals [H,W,3] as RGB ((n + 1) / 2), black where invalid."""
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    unit = normals / np.maximum(length, 1e-6)
    image = ((unit + 1) * 127.5).clip(0, 255).astype(np.uint8)
    ok = (length[..., 0] > 1e-3) if valid is None else valid & (length[..., 0] > 1e-3)
    return np.where(ok[..., None], image, 0).astype(np.uint8)


def read_curves(events_path: Path) -> dict[str, list[tuple[float, float]]]:
    """(step, value) series of loss and psnr from a run's events.jsonl."""
    curves: dict[str, list[tuple[float, float]]] = {"loss": [], "psnr": []}
    if not events_path.is_file():
        return curves
    for line in events_path.read_text(encoding="utf-8").splitlines():
        try:
            event = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line being written while we read
        if event.get("kind") != "progress" or event.get("stage") != "train":
            continue
        for key in curves:
            value = event.get("metrics", {}).get(key)
            if isinstance(value, (int, float)):
                curves[key].append((float(event["step"]), float(value)))
    return curves


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _prior_panels(config: Any, used: Any, rendered_depth: np.ndarray, rendered_valid: np.ndarray,
                  limits: Optional[tuple[float, float]]) -> list[np.ndarray]:
    """The used prior's depth and normal maps for one view, as the losses see them.

    A relative prior (ndn) is aligned to the rendered depth with the scale/shift fit the
    depth loss uses, so its colours share the true depth's scale; sparse samples (sfm) are
    dilated to be visible.
    """
    import torch

    from ..priors.losses import fit_scale_shift

    panels = []
    if used.depth is not None:
        valid = used.mask & (used.depth > 0)
        depth, caption = used.depth, f"{config.priors} depth prior"
        if used.relative_depth:
            both = torch.from_numpy(valid & rendered_valid & (rendered_depth > 0))
            if int(both.sum()) >= 2:
                scale, shift = fit_scale_shift(torch.from_numpy(used.depth.astype(np.float32)),
                                               torch.from_numpy(rendered_depth.astype(np.float32)), both)
                depth = np.where(valid, float(scale) * used.depth + float(shift), 0.0).astype(np.float32)
                caption = f"{config.priors} depth, aligned"
        image = colorize_depth(depth, valid, limits)
        if np.count_nonzero(valid) < 0.2 * valid.size:
            image = cv2.dilate(image, np.ones((3, 3), np.uint8))  # make single-pixel samples visible
            caption += ", dilated"
        panels.append(_label(image, caption))
    if used.normal is not None:
        panels.append(_label(colorize_normals(used.normal, used.mask), f"{config.priors} normal prior"))
    return panels


def geometry_scores(depth: Optional[np.ndarray], normal: Optional[np.ndarray], valid: np.ndarray,
                    truth_depth: np.ndarray, truth_normal: Optional[np.ndarray],
                    truth_mask: np.ndarray) -> dict[str, float]:
    """Depth and normal scores of one map pair against the truth, as NDN is scored (docs/ndn.md).

    ``depth`` [H, W] (metric or relative: aligned to the truth by the robust scale/shift fit
    first), ``normal`` [H, W, 3] camera frame, ``valid`` [H, W] bool where the map has values,
    truth maps of the same size. Returns abs_rel, delta1, normal_mean_deg, normal_within_11_25
    and pixels; a map that is None or has no valid pixel yields no entries for it.
    """
    import torch

    from ..ndn.infer import depth_metrics, normal_metrics

    scores: dict[str, float] = {}
    mask = valid & truth_mask
    if depth is not None:
        depth_mask = mask & (depth > 0) & (truth_depth > 0)
        if np.count_nonzero(depth_mask) >= 2:
            scores.update(depth_metrics(torch.from_numpy(depth.astype(np.float32)),
                                        torch.from_numpy(truth_depth.astype(np.float32)), torch.from_numpy(depth_mask)))
            scores["pixels"] = int(np.count_nonzero(depth_mask))
    if normal is not None and truth_normal is not None:
        normal_mask = mask & (np.linalg.norm(normal, axis=-1) > 1e-3)
        if np.any(normal_mask):
            scores.update(normal_metrics(torch.from_numpy(np.moveaxis(normal, -1, 0).astype(np.float32)),
                                         torch.from_numpy(np.moveaxis(truth_normal, -1, 0).astype(np.float32)),
                                         torch.from_numpy(normal_mask)))
    return scores


_UNSEEN = np.array([255, 0, 255], np.float32)  # magenta: ground no training view saw


def unseen_ground_masks(run_dir: Path, stems: list[str]) -> dict[str, np.ndarray]:
    """{stem: [H, W] bool} ground of each held-out view that no training view saw (see
    :mod:`esgs.core.train.coverage`): the view's true depth where the scene has it (gt priors),
    else its rendered depth, tested against the training views' rendered depth."""
    import torch

    from ..priors import load_prior_maps
    from ..train.coverage import training_depths, unseen_ground
    from ..train.evaluate import load_run

    config, data, model, backend, device = load_run(run_dir)
    views = {view.stem: view for view in data.test}
    truth = SceneDir(Path(config.scene)).has_prior_maps(PriorSource.GT, "depth")
    masks = {}
    with torch.no_grad():
        params = model.render_params(model.max_sh_degree)
        depths = training_depths(params, data.train, backend=backend, device=device)
        for stem in stems:
            if stem not in views:
                continue
            view = views[stem]
            depth = surface = None
            if truth:
                maps = load_prior_maps(Path(config.scene), PriorSource.GT, view.name, size=(view.width, view.height))
                depth, surface = maps.depth, maps.mask
            masks[stem] = unseen_ground(params, view, data.train, backend=backend, device=device, train_depths=depths,
                                        depth=depth, surface=surface)
    return masks


def mark_unseen(image: np.ndarray, unseen: Optional[np.ndarray]) -> np.ndarray:
    """``image`` with unseen ground tinted magenta and outlined (unchanged when nothing is unseen)."""
    image = _rgb(image).copy()
    if unseen is None or not unseen.any() or unseen.shape != image.shape[:2]:
        return image
    tinted = image.astype(np.float32)
    tinted[unseen] = 0.55 * tinted[unseen] + 0.45 * _UNSEEN
    tinted = tinted.round().astype(np.uint8)
    contours, _ = cv2.findContours(unseen.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(tinted, contours, -1, (255, 0, 255), 1)
    return tinted


def _geometry_figure(config: Any, scene: Path, out: Path) -> tuple[str, dict[str, dict[str, float]]]:
    """Truth, the used priors and the ESGS run's rendered depth and normals, one held-out view.

    Rows: the image with the true depth and normals (synthetic scenes); the prior maps of
    ``config.priors`` (unless those are the truth); the ESGS run's rendered depth and normals.
    Returns the picture's file name and, when the scene has true maps, the scores of the
    prior and of the rendering against them (:func:`geometry_scores`), keyed by row label.
    """
    import torch

    from ..priors import available_prior_sources, load_prior_maps
    from ..train.evaluate import load_run
    from ..train.rendering import render_view

    run = config.out / "runs" / "esgs"
    _, data, model, backend, device = load_run(run)
    view = (data.test or data.train)[0]
    with torch.no_grad():
        output = render_view(model.render_params(model.max_sh_degree), view.viewmat.to(device), view.K.to(device),
                             view.width, view.height, render_depth=True, render_normals=True, backend=backend)
    depth = output.depth[..., 0].cpu().numpy()
    alpha = output.alpha[..., 0].cpu().numpy() > 0.5
    normals = output.normals.cpu().numpy()
    image = _label(view.image.cpu().numpy(), f"image {view.name}")
    truth_panels: list[np.ndarray] = []
    limits = None
    rotation = view.viewmat[:3, :3].double().numpy()
    sources = available_prior_sources(scene)
    as_prior = " = prior" if config.priors == "gt" else ""
    truth = None
    if "gt" in sources:
        truth = load_prior_maps(scene, "gt", view.name, size=(view.width, view.height), world_to_camera_rotation=rotation)
        if truth.depth is not None:
            valid = truth.mask & (truth.depth > 0)
            limits = (float(np.percentile(truth.depth[valid], 2)), float(np.percentile(truth.depth[valid], 98)))
            truth_panels.append(_label(colorize_depth(truth.depth, truth.mask, limits), "true depth" + as_prior))
        if truth.normal is not None:
            truth_panels.append(_label(colorize_normals(truth.normal, truth.mask), "true normals" + as_prior))
    rendered = [_label(colorize_depth(depth, alpha, limits), "ESGS depth"),
                _label(colorize_normals(normals, alpha), "ESGS normals")]
    def titled(title: str, panels: list[np.ndarray]) -> np.ndarray:
        # a first column naming the row keeps depth under depth and normals under normals
        block = np.zeros((view.height, view.width, 3), np.uint8)
        cv2.putText(block, title, (4, view.height // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.4, _WHITE, 1, cv2.LINE_AA)
        return _hstack([_label(block, "")] + panels)

    rows = [_hstack([image] + truth_panels)]
    scores: dict[str, dict[str, float]] = {}
    used = None
    if config.priors != "gt" and config.priors in sources:
        used = load_prior_maps(scene, config.priors, view.name, size=(view.width, view.height),
                               world_to_camera_rotation=rotation)
        prior = _prior_panels(config, used, depth, alpha, limits)
        if prior:
            rows.append(titled(f"{config.priors} priors", prior))
    rows.append(titled("ESGS rendering", rendered))
    path = out / "geometry.png"
    write_png(path, _vstack(rows))
    if truth is not None and truth.depth is not None:
        if used is not None:
            scores[f"`{config.priors}` prior"] = geometry_scores(used.depth, used.normal, used.mask, truth.depth,
                                                                  truth.normal, truth.mask)
        scores["ESGS rendering"] = geometry_scores(depth, normals, alpha, truth.depth, truth.normal, truth.mask)
    return path.name, scores


def _esgs_terms(config: Any) -> str:
    """The ESGS switches of the run as words, from its saved config.json (what actually trained)."""
    from ..errors import ConfigError
    from ..methods import load_run_config

    try:
        saved = load_run_config(RunDir(config.out / "runs" / "esgs").config)
    except ConfigError:
        return "settings unknown"
    esgs = vars(saved.method_config) if saved.method == "esgs" else {}
    names = (("depth", "depth-prior loss"), ("normal", "normal-prior loss"),
             ("consistency", "depth-normal consistency loss"), ("gpdfn", "GPDFN"))
    used = [words for key, words in names if esgs.get(key)]
    return ", ".join(used) if used else "no ESGS terms"


def _auto_priors_paragraph(scene: Path) -> str:
    """What the ``auto`` priors were made of, from ``priors/auto/auto.json``."""
    from ..priors.auto import read_report, summary_line

    text = ("The `auto` priors fuse, per pixel, stereo labels (a mesh rebuilt from the images), NDN depth "
            "pinned to each view's SfM points and the SfM points themselves, each weighted by a confidence "
            "from its agreement with the SfM points; ESGS scales its depth loss by it.")
    record = read_report(scene)
    if record is None:
        return text
    try:
        text += f" Here: {summary_line(record).removeprefix('auto priors: ')}."
    except (KeyError, TypeError, ValueError):
        pass  # a report of another version: its numbers are left out, not the report
    skipped = record.get("skipped") or {}
    if skipped:
        text += " Left out: " + "; ".join(f"{source} ({why})" for source, why in skipped.items()) + "."
    if "ndn" in (record.get("sources_used") or []):
        text += f" NDN: {_ndn_weights(scene)}."
    return text


def _ndn_weights(scene: Path) -> str:
    """Which NDN weights wrote the scene's ndn priors, from a depth map's EXR header."""
    from ..ndn.infer import made_by_package, ndn_priors_header

    header = ndn_priors_header(scene)
    weights, normals = header.get("weights", ""), header.get("normal_weights", "")
    if made_by_package(header):
        text = ("the depth network shipped in the package, trained on our synthetic Mars scenes only; see "
                "docs/ndn_model_card.md")
        if normals:
            text += ("; normals from the shipped completion network, which also reads the SfM points and stereo "
                     "labels (docs/ndn_completion_model_card.md)")
        return text
    if not weights:
        return "weights not recorded"
    return f"weights `{weights}`" + (f", normals from `{normals}`" if normals else "")


def _is_synthetic(scene: Path) -> bool:
    try:
        return json.loads(SceneDir(scene).provenance.read_text()).get("source") == "synthetic"
    except (OSError, json.JSONDecodeError):
        return False


def _sparse_points_record(scene: Path) -> Optional[dict]:
    """``scene.json``'s record of triangulated SfM points (None for the generator's exact points)."""
    try:
        record = json.loads(SceneDir(scene).provenance.read_text()).get("sparse_points")
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and "points" in record else None


def write_report(config: Any, scene: Path, runs: dict[str, dict], distances: dict[str, dict],
                 blender: Optional[dict], timings: dict[str, float]) -> Path:
    """Write ``OUT/report.md`` and its pictures under ``OUT/report/``; returns the Markdown path."""
    out = config.out / "report"
    out.mkdir(parents=True, exist_ok=True)
    lines = ["# ESGS demo report", "",
             f"Synthetic Mars scene `{config.preset}` (seed {config.seed}, {config.views} views at "
             f"{config.width}x{config.height}); {config.iterations} training steps per method on "
             f"{platform.processor() or platform.machine()} ({time.strftime('%Y-%m-%d %H:%M')}). "
             f"ESGS used the `{config.priors}` priors ({_esgs_terms(config)}). Every 8th view (sorted by name) "
             "is held out.", ""]
    if config.priors == "ndn":
        lines += [f"The `ndn` priors are predicted by the NDN diffusion network ({_ndn_weights(scene)}): dense "
                  "depth known up to scale and shift, which training pins to the scene's scale with each image's SfM "
                  "points, and camera-frame normals.", ""]
    if config.priors == "auto":
        lines += [_auto_priors_paragraph(scene), ""]
    points = _sparse_points_record(scene)
    if points:
        lines += [f"The scene's {points['points']:,} SfM points were triangulated from its rendered images with the "
                  f"known poses (mean reprojection error {points['mean_reprojection_error_px']:.2f} px), as a real "
                  "capture would give them; they start both runs and pin the relative priors.", ""]
    elif _is_synthetic(scene):
        lines += ["Note: the scene's SfM points are the generator's exact surface samples (triangulation was "
                  "not asked for or found no points), which flatters every method's distance to the mesh.", ""]
    if not points and config.priors == "sfm" and _is_synthetic(scene):
        lines += ["Note: in a synthetic scene the COLMAP points are sampled on the true surface, so the `sfm` "
                  "prior here is sparse but exact depth; on real images it carries SfM's errors.", ""]

    lines += ["## Metrics", "",
              "| method | PSNR (dB) | SSIM | LPIPS | Gaussians | train time (s) | mean dist | std dist | F-score |",
              "|---|---|---|---|---|---|---|---|---|"]
    for name, result in runs.items():
        metrics = result.get("metrics") or {}
        dist = distances.get(name, {})
        filtered = dist.get("gaussians_to_mesh_filtered") or dist.get("gaussians_to_mesh") or {}
        lines.append(f"| {name} | {_fmt(metrics.get('psnr'), 2)} | {_fmt(metrics.get('ssim'))} | "
                     f"{_fmt(metrics.get('lpips'))} | {result.get('n_gaussians', 'n/a'):,} | "
                     f"{_fmt(result.get('elapsed_s'), 0)} | {_fmt(filtered.get('mean'))} | {_fmt(filtered.get('std'))} | "
                     f"{_fmt(dist.get('fscore'))} |")
    lines += ["", "Distances are from Gaussian centres (opacity >= 0.5) to the ground-truth mesh, in metres; the "
              "F-score combines both directions at a 5 cm threshold. LPIPS is AlexNet v0.1 (n/a when its "
              "weights could not be obtained).", ""]

    # held-out renders beside the ground truth, with a magnified crop
    test_dir = RunDir(config.out / "runs" / "esgs").test_renders
    held_out = [path.name[: -len("_gt.png")] for path in sorted(test_dir.glob("*_gt.png"))[:3]]
    try:
        unseen_masks = unseen_ground_masks(config.out / "runs" / "esgs", held_out)
    except Exception as error:  # noqa: BLE001 - the pictures still help without the marks
        print(f"warning: the report's held-out pictures have no unseen-ground marks: {error}", flush=True)
        unseen_masks = {}
    for stem in held_out:
        unseen = unseen_masks.get(stem)
        images = [("ground truth", read_image(test_dir / f"{stem}_gt.png"))]
        for name, folder in (("ESGS", "esgs"), ("3DGS", "3dgs")):
            path = RunDir(config.out / "runs" / folder).test_render(stem)
            if path.is_file():
                images.append((name, mark_unseen(read_image(path), unseen)))
        height, width = images[0][1].shape[:2]
        box = (width // 2 - width // 8, height // 2 - height // 8, width // 4, height // 4)
        top = _hstack([_label(image, name) for name, image in images])
        bottom = _hstack([_label(magnified_crop(image, box, 2), f"{name} x2 crop") for name, image in images])
        figure = out / f"heldout_{stem}.png"
        write_png(figure, _vstack([top, bottom]))
        lines += [f"## Held-out view `{stem}`", "", f"![held-out {stem}](report/{figure.name})", ""]
        if unseen is not None and unseen.any():
            lines += [f"Magenta on the renders: ground that no training view saw ({100 * unseen.mean():.1f} % of the "
                      "view); no method can reconstruct it, so its colour there is a guess.", ""]

    snapshots = sorted((out / "snapshots").glob("step_*.png"))
    if snapshots:
        strip = _hstack([_label(read_image(p), f"step {int(p.stem.split('_')[1])}") for p in snapshots])
        write_png(out / "training_progress.png", strip)
        lines += ["## One held-out view during ESGS training", "", "![training](report/training_progress.png)", ""]

    try:
        name, scores = _geometry_figure(config, scene, out)
        lines += ["## Geometry: priors and rendered depth / normals", "",
                  "The first held-out view: truth (top), the priors ESGS trained with, and the ESGS run's rendered "
                  "depth and normals (bottom). Camera-frame normals are shown as (n + 1) / 2; depth is coloured "
                  "near = red, far = blue, on the true depth's range; for this picture a relative prior (ndn) is "
                  "aligned to the rendered depth by a scale/shift fit (training pins it to the SfM points).", "", f"![geometry](report/{name})", ""]
        if scores:
            lines += ["| on this view, against the truth | AbsRel | delta1 | normal error (deg) | < 11.25 deg |",
                      "|---|---|---|---|---|"]
            for label, row in scores.items():
                within = row.get("normal_within_11_25")
                lines.append(f"| {label} | {_fmt(row.get('abs_rel'))} | {_fmt(row.get('delta1'), 3)} | "
                             f"{_fmt(row.get('normal_mean_deg'), 1)} | "
                             f"{'n/a' if within is None else f'{100 * within:.1f} %'} |")
            lines += ["", "Depth is scored after a robust scale/shift fit to the true depth (as `esgs ndn eval` "
                      "scores NDN), over the pixels where both maps have values.", ""]
    except Exception as error:  # noqa: BLE001 - a figure must not sink the whole report
        lines += ["## Geometry", "", f"(figure not made: {error})", ""]

    from .plots import curves_image, write_heat_map

    read = {name: read_curves(RunDir(config.out / "runs" / folder).events)
            for name, folder in (("ESGS", "esgs"), ("3DGS", "3dgs")) if (config.out / "runs" / folder).is_dir()}
    write_png(out / "curves.png", curves_image({key: {name: curves[key] for name, curves in read.items()}
                                                for key in ("loss", "psnr")}))
    lines += ["## Training curves", "", "Training loss (log scale) and PSNR (dB) on the training views against the "
              "step, per method (moving averages, as the progress line prints them).", "",
              "![curves](report/curves.png)", ""]

    if blender and Path(blender.get("heat_map", "")).is_file():
        heat = out / "heat_map.png"
        saturation, what = write_heat_map(Path(blender["heat_map"]), blender, heat)
        lines += ["## Distance heat map (Blender)", "",
                  "ESGS Gaussian centres coloured by distance to the ground-truth mesh: blue = 0 m, red = "
                  f"{saturation:.3g} m (the {what} of the distances) and beyond; the bar beside the render gives "
                  f"the scale. Open `{Path(blender['blend']).relative_to(config.out)}` in Blender 5.0 to inspect it.",
                  "", "![heat map](report/heat_map.png)", ""]

    lines += ["## Timings", "", "| stage | wall (s) | CPU (s) |", "|---|---|---|"]
    for key, value in timings.items():
        if key.endswith("_cpu_s"):
            continue
        cpu = timings.get(key[:-2] + "_cpu_s")
        lines.append(f"| {key[:-2]} | {value:.0f} | {'n/a' if cpu is None else f'{cpu:.0f}'} |")
    lines += ["", "CPU time counts every thread of the demo and its child processes (scene rendering, Blender); "
              "on a busy machine it is the fairer figure.", ""]
    lines += ["", "Reproduce: `make demo` (or `esgs demo --out DIR`); settings in `demo_config.json`.", ""]
    report = config.out / "report.md"
    atomic_write_text(report, "\n".join(lines))
    from ..config import save_config

    save_config(config, config.out / "demo_config.json")
    return report
