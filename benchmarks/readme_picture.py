"""The README's picture from a demo report: its held-out views, geometry panels, heat map and curves in one JPEG.

    python benchmarks/readme_picture.py demo_output/report --out docs/images/demo_report.jpg

Takes, from the report folder ``make demo`` writes (``demo_output/report``), the first held-out
view figure, ``geometry.png`` (true depth and normals, the priors, ESGS's rendered depth and
normals), ``heat_map.png`` (the distance heat map with its colour bar in metres) and
``curves.png`` (loss and PSNR with axes and legends), each scaled to one width and stacked.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np


def stack(paths: list[Path], width: int) -> np.ndarray:
    """The images at ``paths``, each scaled to ``width`` pixels, one under the other on white."""
    rows = []
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise SystemExit(f"cannot read {path}")
        height = max(1, round(image.shape[0] * width / image.shape[1]))
        rows.append(cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA))
        rows.append(np.full((8, width, 3), 255, np.uint8))
    return np.vstack(rows[:-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("report", type=Path, help="the demo's report folder (demo_output/report)")
    parser.add_argument("--out", type=Path, default=Path("docs/images/demo_report.jpg"))
    parser.add_argument("--width", type=int, default=1200)
    args = parser.parse_args(argv)
    held_out = sorted(args.report.glob("heldout_*.png"))[:1]
    panels = [*held_out, *(args.report / name for name in ("geometry.png", "heat_map.png", "curves.png"))]
    missing = [path for path in panels if not path.is_file()]
    if missing or not held_out:
        raise SystemExit(f"not a finished demo report: missing {', '.join(map(str, missing)) or 'heldout_*.png'}")
    picture = stack(panels, args.width)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    temporary = args.out.with_name(args.out.name + ".part.jpg")
    if not cv2.imwrite(str(temporary), picture, [cv2.IMWRITE_JPEG_QUALITY, 85]):
        raise SystemExit(f"cannot write {args.out}")
    temporary.replace(args.out)
    print(f"{args.out}: {picture.shape[1]}x{picture.shape[0]} from {', '.join(path.name for path in panels)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
