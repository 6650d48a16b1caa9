"""``esgs train SCENE --out RUN_DIR``: train Gaussians on a COLMAP scene (3DGS baseline)."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "train Gaussians on a COLMAP scene folder (images/ + sparse/0) into a run folder"

#: Settings given as positional arguments or handled here rather than as plain flags.
_SKIPPED = ("scene", "esgs", "baselines")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..config import add_dataclass_arguments
    from ..train.config import TrainConfig

    parser.add_argument("scene", type=Path, help="COLMAP scene folder (images/ + sparse/0)")
    add_dataclass_arguments(parser, TrainConfig, skip=_SKIPPED)
    from ..method.config import ESGSConfig

    esgs_group = parser.add_argument_group("ESGS", "prior losses and GPDFN (all off = the 3DGS baseline)")
    add_dataclass_arguments(esgs_group, ESGSConfig)
    from ..baselines.config import BaselinesConfig

    baselines_group = parser.add_argument_group("comparison methods", "Mip-Splatting and DropoutGS (docs/baselines.md)")
    add_dataclass_arguments(baselines_group, BaselinesConfig)
    parser.add_argument("--config", dest="config_file", type=Path, default=None,
                        help="read settings from a JSON file (flags given here override it)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def build_config(args: argparse.Namespace):
    """The TrainConfig of a command line: a resumed run's config.json (or --config), then flags."""
    from ..config import config_from_dict, dataclass_from_args, load_config
    from ..errors import ConfigError
    from ..train.config import TrainConfig, load_run_config
    from ..train.run_dir import RunDir

    if args.out is None:
        raise ConfigError("--out is required", hint="esgs train SCENE --out RUN_DIR")
    base = None
    if args.resume and RunDir(args.out).config.is_file():
        # a resumed run keeps the settings it was started with; flags override the safe ones
        base = load_run_config(RunDir(args.out).config)
    elif args.config_file is not None:
        base = load_config(TrainConfig, args.config_file)
    from ..method.config import ESGSConfig

    config = dataclass_from_args(TrainConfig, args, base=base)
    from ..baselines.config import BaselinesConfig

    esgs = dataclass_from_args(ESGSConfig, args, base=config.esgs)
    baselines = dataclass_from_args(BaselinesConfig, args, base=config.baselines)
    values = {**_as_dict(config), "scene": Path(args.scene), "esgs": _as_dict(esgs), "baselines": _as_dict(baselines)}
    return config_from_dict(TrainConfig, values)


def _as_dict(config) -> dict:
    from ..config import config_to_dict

    return config_to_dict(config)


def run(args: argparse.Namespace) -> int:
    from ..progress import ConsoleProgress
    from ..train import train

    config = build_config(args)
    console = None if args.quiet else ConsoleProgress()
    try:
        result = train(config, progress=console)
    finally:
        if console is not None:
            console.close()
    if result.status == "interrupted":
        print(f"stopped at step {result.step}/{result.iterations}; checkpoint saved, "
              f"continue with: esgs train {config.scene} --out {config.out} --resume")
        return 143  # 128 + SIGTERM: stopped on request, resumable
    line = f"{result.status}: {result.step} steps, {result.n_gaussians:,} Gaussians, {result.elapsed_s:.0f} s"
    if result.metrics:
        metrics = result.metrics
        lpips = "n/a" if metrics.get("lpips") is None else f"{metrics['lpips']:.4f}"
        line += f"; {metrics['split']} PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}, LPIPS {lpips}"
    print(line)
    print(f"wrote {result.point_cloud}")
    return 0
