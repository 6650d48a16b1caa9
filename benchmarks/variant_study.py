"""Variants of the trainer that were measured and not shipped: one run per call, then a JSON of them all.

The variants patch the engine in this process only (nothing here is an option of the
engine): they were tried against the defaults on tuning scenes, lost, and are kept so the
figures in the docs can be re-made.

Depth-prior variants (issue 23, "the log-depth sink": the depth prior moves opaque Gaussians
below the surface on outdoor scenes with rover views); each changes only ESGS's depth term:

- ``centre``: as shipped (the composited centre depth, log L1);
- ``graze``: each pixel's error times ``|n_prior . ray|`` (a grazing ray turns a small height
  error into a large depth error), not renormalised, so the view's pull also drops;
- ``graze2``: the same with the cosine squared;
- ``grazen``: the cosine as a relative weight (renormalised over the view, like the edge weights);
- ``plane``: PGSR's unbiased depth (the depth where the ray meets the composited plane of the
  Gaussians' shortest axes) in place of the centre depth;
- ``planegraze``: ``plane`` with the ``graze`` weights;
- ``aerial``: the depth prior only on views with no sky (the rover views left out).

Sky variant (issue 22): ``sky-above-horizon``: the sky model multiplied by a ramp that is 1
above -5 degrees of elevation (world +Z up) and 0 below -15 degrees (black), so the sky cannot
show through the ground of the aerial views.

    python benchmarks/variant_study.py run VARIANT SCENE OUT SEED [--arm depth|full|3dgs]
        [--iterations 600] [--priors gt] [--sky-unseen-weight W] > OUT.txt
    python benchmarks/variant_study.py collect JSON LOG ...

``run`` trains one run (2 threads) and prints a ``RESULT {...}`` line: held-out PSNR / SSIM /
LPIPS, Gaussian count, and the opaque centres' (opacity >= 0.5) distance to the scene's mesh
(mean, median, share below it along the closest face's normal, of 4,000 drawn with seed 0);
for scenes with gt sky masks also the PSNR of held-out views with and without sky and the sky
error. ``collect`` gathers the RESULT lines of the logs into one JSON with the commands.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import os

# idle OpenMP threads spin by default and take the cores a busy machine's other runs need
# (docs/rasterizer.md, "Spinning OpenMP workers"); set before torch loads
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

DEPTH_VARIANTS = ("centre", "graze", "graze2", "grazen", "plane", "planegraze", "aerial")
SKY_VARIANTS = ("sky-above-horizon",)


def _ray_cosines() -> Any:
    """A cache of ``|n_prior . ray|`` per view: [H, W] from the prior's camera-frame normals."""
    import torch

    cache: dict[str, Any] = {}

    def cosines(context: Any, prior: Any) -> Any:
        name = context.view.name
        if name not in cache:
            K = context.view.K.double()
            height, width = prior.depth.shape
            v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                                  torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
            rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
            rays = rays / rays.norm(dim=-1, keepdim=True)
            normals = prior.normal.double()
            normals = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-6)
            cache[name] = (normals * rays).sum(-1).abs().float()
        return cache[name]

    return cosines


def patch_depth_term(variant: str) -> None:
    """Replace ESGS's depth term by ``variant`` (see the module's docstring)."""
    from esgs.core.methods.esgs import prior_hook
    from esgs.core.priors.losses import depth_loss

    hook = prior_hook.PriorLossHook
    shipped = hook._depth_term
    cosines = _ray_cosines()
    if variant == "centre":
        return
    if variant == "aerial":
        def term(self: Any, context: Any) -> Any:
            prior = self.priors.get(context.view.name)
            if prior is not None and bool((~prior.mask).any()):  # the gt mask marks the sky of rover views
                return context.image.sum() * 0.0
            return shipped(self, context)
        hook._depth_term = term
        return
    if variant in ("graze", "graze2", "grazen"):
        power = 2.0 if variant == "graze2" else 1.0

        def term(self: Any, context: Any) -> Any:
            prior = self.priors.get(context.view.name)
            if prior is None or prior.depth is None or context.depth is None:
                return context.image.sum() * 0.0
            weights, confidence = self._edge_weights(context), prior.confidence
            if variant == "grazen":
                weights = weights * cosines(context, prior)
            else:
                cosine = cosines(context, prior) ** power
                confidence = cosine if confidence is None else confidence * cosine
            return depth_loss(context.depth[..., 0], prior.depth, prior.mask, weights, mode=self.config.depth_mode,
                              relative=prior.relative, alpha=context.alpha[..., 0], confidence=confidence)
        hook._depth_term = term
        return
    if variant in ("plane", "planegraze"):
        from esgs.core.methods.baselines.pgsr import plane_features, unbiased_depth

        def before_render(self: Any, run: Any, context: Any, params: Any) -> Any:
            if not self.config.depth:
                return params
            return replace(params, extra=plane_features(params.means, params.quats, params.scales,
                                                        context.view.viewmat.to(params.means)))

        def term(self: Any, context: Any) -> Any:
            prior = self.priors.get(context.view.name)
            extra = context.output.extra if context.output is not None else None
            if prior is None or prior.depth is None or extra is None:
                return context.image.sum() * 0.0
            depth, valid = unbiased_depth(extra[..., :3], extra[..., 3], context.view.K.to(extra))
            confidence = prior.confidence
            if variant == "planegraze":
                cosine = cosines(context, prior)
                confidence = cosine if confidence is None else confidence * cosine
            return depth_loss(depth, prior.depth, prior.mask & valid, self._edge_weights(context),
                              mode=self.config.depth_mode, relative=prior.relative, alpha=context.alpha[..., 0],
                              confidence=confidence)
        hook.before_render = before_render
        hook._depth_term = term
        return
    raise SystemExit(f"unknown depth variant {variant!r}")


def patch_sky_above_horizon(low_deg: float = -15.0, high_deg: float = -5.0) -> None:
    """The sky model times a ramp in elevation (world +Z up): 0 below ``low_deg``, 1 above ``high_deg``."""
    from esgs.core.train import sky

    low, high = math.sin(math.radians(low_deg)), math.sin(math.radians(high_deg))
    shipped = sky.SkyModel.forward

    def forward(self: Any, directions: Any) -> Any:
        colour = shipped(self, directions)
        return colour * ((directions[..., 2:3].to(colour) - low) / (high - low)).clamp(0.0, 1.0)

    sky.SkyModel.forward = forward


def run(args: argparse.Namespace) -> int:
    if args.variant in SKY_VARIANTS:
        patch_sky_above_horizon()
    else:
        patch_depth_term(args.variant)
    from esgs.core.experiments.runs import RunTask, run_task
    from esgs.core.formats.ply import read_gaussians_ply
    from esgs.core.formats.run_dir import RunDir
    from esgs.core.formats.scene_dir import SceneDir
    from esgs.core.methods import full_esgs
    from esgs.core.metrics.geometry import load_mesh, point_to_mesh_distances

    config: dict[str, Any] = {"lpips": True, "save_renders": False, "checkpoint_every": 0,
                              "iterations": args.iterations, "backend": "cpu", "threads": 2, "seed": args.seed}
    if args.sky_unseen_weight:
        config["sky_unseen_weight"] = args.sky_unseen_weight
    if args.arm != "3dgs":
        settings = full_esgs(args.priors)
        if args.arm == "depth":
            settings = replace(settings, normal=False, gpdfn=False)
        config.update(method="esgs", method_config=asdict(settings))
    summary = run_task(RunTask(name=args.out.name, scene=args.scene, out=args.out, config=config, seed=args.seed,
                               measure_render=False))
    result: dict[str, Any] = {"variant": args.variant, "arm": args.arm, "scene": args.scene.name, "seed": args.seed,
                              "iterations": args.iterations, "priors": args.priors if args.arm != "3dgs" else None,
                              "sky_unseen_weight": args.sky_unseen_weight,
                              **{key: summary.get(key) for key in ("psnr", "ssim", "lpips", "n_gaussians")}}
    gaussians = read_gaussians_ply(RunDir(args.out).point_cloud)
    keep = 1.0 / (1.0 + np.exp(-gaussians.opacity_logit.reshape(-1))) >= 0.5
    centres = gaussians.means[keep].astype(np.float64)
    mesh_path = SceneDir(args.scene).ground_truth_mesh
    distances = point_to_mesh_distances(centres, *load_mesh(str(mesh_path)))
    result.update(opaque=int(keep.sum()), distance_mean=float(distances.mean()),
                  distance_median=float(np.median(distances)), below=_share_below(centres, mesh_path))
    if SceneDir(args.scene).has_prior_maps("gt", "mask"):
        sys.path.insert(0, str(Path(__file__).parent))
        from sky_study import sky_error

        sky = sky_error(args.out, args.scene)
        views = sky.get("views") or []
        with_sky = [v["psnr"] for v in views if v["sky_fraction"] >= 0.01]
        without = [v["psnr"] for v in views if v["sky_fraction"] < 0.01]
        result.update(sky_mae=sky.get("sky_mae"), psnr_sky_views=float(np.mean(with_sky)) if with_sky else None,
                      psnr_ground_views=float(np.mean(without)) if without else None)
    print("RESULT " + json.dumps(result), flush=True)
    return 0


def _share_below(centres: np.ndarray, mesh_path: Path) -> float:
    """Share of (4,000 drawn) centres below the mesh along the closest face's normal."""
    import trimesh

    sys.path.insert(0, str(Path(__file__).parent))
    from esgs_prior_ablation import signed_distances

    return 1.0 - signed_distances(centres, trimesh.load(str(mesh_path), force="mesh"))["above_share"]


def collect(args: argparse.Namespace) -> int:
    from esgs.core.io_utils import atomic_write_json

    rows = []
    for log in args.logs:
        for line in Path(log).read_text().splitlines():
            if line.startswith("RESULT "):
                rows.append({"log": str(log), **json.loads(line[len("RESULT "):])})
    atomic_write_json(args.json, {"what": __doc__.split("\n\n")[0], "command": " ".join(sys.argv),
                                  "note": args.note, "rows": rows})
    print(f"{len(rows)} runs -> {args.json}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    one = commands.add_parser("run", help="train one run with a variant and print its RESULT line")
    one.add_argument("variant", choices=DEPTH_VARIANTS + SKY_VARIANTS)
    one.add_argument("scene", type=Path)
    one.add_argument("out", type=Path)
    one.add_argument("seed", type=int)
    one.add_argument("--arm", choices=("depth", "full", "3dgs"), default="depth",
                     help="depth: ESGS with the depth prior alone; full: full ESGS; 3dgs: the defaults")
    one.add_argument("--iterations", type=int, default=600)
    one.add_argument("--priors", default="gt")
    one.add_argument("--sky-unseen-weight", type=float, default=0.0)
    gather = commands.add_parser("collect", help="gather RESULT lines of logs into a JSON")
    gather.add_argument("json", type=Path)
    gather.add_argument("logs", nargs="+", type=Path)
    gather.add_argument("--note", default="")
    args = parser.parse_args(argv)
    return run(args) if args.command == "run" else collect(args)


if __name__ == "__main__":
    raise SystemExit(main())
