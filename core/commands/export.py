"""``esgs export``: a run's Gaussians in a format other 3DGS tools and web viewers open."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "export a run's Gaussians for other tools: the 3DGS PLY, the web viewers' .splat, or Niantic's SPZ"

FORMATS = ("ply", "splat", "spz")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="run folder (its point_cloud.ply is read) or a 3DGS PLY file")
    parser.add_argument("--format", choices=FORMATS, default="ply",
                        help="ply: the standard 3DGS PLY (all SH bands); splat: antimatter15's .splat (32 bytes a "
                             "Gaussian, base colour only) for web viewers and SuperSplat; spz: Niantic's compressed SPZ "
                             "(all SH bands, quantised to bytes; needs pip install gsply) (default: ply)")
    parser.add_argument("--out", type=Path, default=None,
                        help="file to write (default: <run folder name>.<format> in the current folder); "
                             "an existing file is replaced, atomically")


def source_ply(location: Path) -> Path:
    """The PLY to export: ``RUN/point_cloud.ply`` of a run folder, or ``location`` itself when it is a file."""
    from ..errors import DatasetError
    from ..formats.run_dir import RunDir

    location = Path(location)
    if location.is_dir():
        path = RunDir(location).point_cloud
        if not path.is_file():
            raise DatasetError("the run folder has no point_cloud.ply", path=location,
                               hint="export a finished (or stopped) run; training writes it at the end")
        return path
    if not location.is_file():
        raise DatasetError("no such run folder or PLY file", path=location)
    return location


def default_out(location: Path, fmt: str) -> Path:
    """``<name>.<fmt>`` in the current folder: the run folder's name, or the PLY file's stem."""
    location = Path(location).resolve()
    return Path(f"{location.name if location.is_dir() else location.stem}.{fmt}")


def run(args: argparse.Namespace) -> int:
    from ..errors import ConfigError
    from ..formats.ply import read_gaussians_ply, write_gaussians_ply
    from ..formats.splat import write_splat
    from ..formats.spz import gsply_module, spz_clipped, write_spz

    if args.format == "spz":
        gsply_module()  # the optional package, asked for before any reading
    source = source_ply(args.run)
    out = Path(args.out) if args.out is not None else default_out(args.run, args.format)
    if out.exists() and out.resolve() == source.resolve():
        raise ConfigError("--out is the file being exported", path=out, hint="choose another --out")
    gaussians = read_gaussians_ply(source)  # any 3DGS PLY (property order, doubles): checked and normalised
    note = ""
    if args.format == "ply":
        write_gaussians_ply(out, gaussians)
    elif args.format == "splat":
        write_splat(out, gaussians)
    else:
        bits = write_spz(out, gaussians)
        clipped = {name: count for name, count in spz_clipped(gaussians).items() if count}
        note = f", positions to 1/{1 << bits}"
        if clipped:
            note += ", clipped to SPZ's ranges: " + ", ".join(f"{count} {name}" for name, count in clipped.items())
    print(f"wrote {out} ({args.format}, {len(gaussians)} Gaussians, {out.stat().st_size / 1e6:.1f} MB{note})")
    return 0
