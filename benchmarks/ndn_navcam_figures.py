"""NDN on real Curiosity Navcam frames: predicted depth and normals as small PNGs for docs/.

The scene is the Navcam station of ../shared/data/mars_navcam_pan registered by
``esgs dataset rotation-only`` (one camera centre, so each frame's two neighbours are the
frames pointing closest to it). For a few frames this writes
``docs/images/ndn_navcam_<stem>.png``: the frame | predicted relative depth (turbo
colour map, dark blue = near, red = far, black = no surface) | predicted normals
(camera frame, RGB = (n + 1) / 2 with OpenCV axes) | with weights that have a sky head, the
sky probability (white = sky; the depth and normal panels are black where it is above one
half), each 192 px wide.

    esgs dataset rotation-only ../shared/data/mars_navcam_pan/images --out STATION --focal-px 621
    .venv/bin/python benchmarks/ndn_navcam_figures.py STATION [--weights W] [--frames 4]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: where the documentation keeps its figures (a docs folder, not a scene folder's images/)
DOC_FIGURES = REPO.joinpath("docs", "images")
PANEL = 192


def navcam_figures(scene_dir: Path, out_dir: Path, weights=None, frames: int = 4, seed: int = 0,
                   prefix: str = "ndn_navcam") -> list[Path]:
    """Write one PNG per chosen frame (evenly spaced over the sorted names); returns the paths."""
    import cv2
    import torch

    from esgs.core.formats.imageio import read_image, write_png
    from esgs.core.ndn.data import centre_as_neighbours, scene_triples
    from esgs.core.ndn.infer import maps_from_states
    from esgs.core.ndn.shipped import resolve_default_weights
    from esgs.core.ndn.train import load_checkpoint
    from esgs.core.formats.scene_dir import SceneDir

    model, diffusion, config, _ = load_checkpoint(resolve_default_weights(weights))
    triples = scene_triples(scene_dir, config.model.working_size, 2 ** (config.model.levels - 1), with_targets=False)
    picks = np.linspace(0, len(triples.names) - 1, frames).round().astype(int)
    views = torch.from_numpy(triples.views[picks].astype(np.float32) / 127.5 - 1.0)
    if triples.one_centre and config.model.panorama_input == "centre":
        views = centre_as_neighbours(views)  # as esgs priors feeds it a panorama
    depth_states, normal_states, sky = diffusion.sample(model, views, seed=seed, return_sky=True)
    paths = []
    for row, index in enumerate(picks):
        name = triples.names[index]
        image = read_image(SceneDir(scene_dir).image(name))
        rgb = np.repeat(image[..., None], 3, axis=-1) if image.ndim == 2 else image[..., :3]
        small = cv2.resize(rgb, (PANEL, round(PANEL * rgb.shape[0] / rgb.shape[1])), interpolation=cv2.INTER_AREA)
        relative, normal, mask = maps_from_states(depth_states[row, 0].numpy(), normal_states[row].numpy(), small,
                                                  kind=config.diffusion.depth_state,
                                                  log_range=config.diffusion.log_depth_range)
        panels = []
        if sky is not None:
            sky_probability = np.clip(cv2.resize(sky[row, 0].numpy(), small.shape[1::-1], interpolation=cv2.INTER_LINEAR),
                                      0.0, 1.0)
            mask &= sky_probability <= 0.5
            panels.append(np.repeat((sky_probability * 255).astype(np.uint8)[..., None], 3, axis=-1))
        # colour by the view's own depth range: affine states give [1, 2], log states exp(c * state)
        low, high = np.percentile(relative[mask], (1, 99)) if mask.any() else (0.0, 1.0)
        depth_byte = np.clip((relative - low) / max(high - low, 1e-6) * 255.0, 0, 255).astype(np.uint8)
        depth_rgb = cv2.applyColorMap(depth_byte, cv2.COLORMAP_TURBO)[..., ::-1]
        depth_rgb[~mask] = 0
        normal_rgb = np.clip((normal + 1.0) * 127.5, 0, 255).astype(np.uint8)
        normal_rgb[~mask] = 0
        path = out_dir / f"{prefix}_{Path(name).stem}.png"
        write_png(path, np.concatenate([small, depth_rgb, normal_rgb, *panels], axis=1))
        paths.append(path)
    return paths


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path, help="the registered Navcam station (esgs dataset rotation-only)")
    parser.add_argument("--out", type=Path, default=DOC_FIGURES)
    parser.add_argument("--weights", default=None, help="default: the shipped weights")
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--prefix", default="ndn_navcam", help="file name prefix of the figures")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    for path in navcam_figures(args.scene, args.out, args.weights, args.frames, prefix=args.prefix):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
