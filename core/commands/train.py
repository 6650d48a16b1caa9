"""``esgs train SCENE --out RUN_DIR [--method NAME]``: train Gaussians on a COLMAP scene."""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

HELP = "train Gaussians on a COLMAP scene folder (images/ + sparse/0) into a run folder"

#: Settings given as positional arguments or handled here rather than as plain flags.
_SKIPPED = ("scene", "method", "method_config")

#: Switches of the layout before methods were registered: each still chooses its method.
_METHOD_SWITCHES = {"mip_splatting": "mip-splatting", "dropout_gs": "dropout-gs"}


def _settings_classes() -> dict[str, type]:
    """Method name -> settings dataclass, for every registered method that has settings."""
    from ..methods import get_method, method_names

    return {name: get_method(name).settings_class for name in method_names() if get_method(name).settings_class}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..config import add_dataclass_arguments
    from ..methods import get_method, method_names
    from ..train.config import TrainConfig

    parser.add_argument("scene", type=Path, nargs="?", help="COLMAP scene folder (images/ + sparse/0)")
    add_dataclass_arguments(parser, TrainConfig, skip=_SKIPPED)
    parser.add_argument("--method", choices=method_names(), default=None,
                        help="training method (default: 3dgs, or the method whose flags are given); "
                             "--method esgs starts from the full method for --priors (esgs.core.methods.full_esgs)")
    parser.add_argument("--esgs", action="store_true",
                        help="full ESGS on the best priors the images allow: the same as --method esgs --priors auto "
                             "(depth + normal priors + GPDFN; priors/auto is computed first when missing or stale)")
    parser.add_argument("--list-methods", action="store_true", help="list the training methods and exit")
    parser.add_argument("--vanilla", action="store_true",
                        help="the published method's own settings, for comparisons with other tools (with the "
                             "default method: plain 3DGS): no sky model, no sky masks and no pruning of hidden "
                             "Gaussians (--sky none --mask-source none --prune-hidden 0; "
                             "esgs.core.train.config.VANILLA_3DGS)")
    seen: set[str] = set()
    for name, settings_class in _settings_classes().items():
        group = parser.add_argument_group(f"method {name}", get_method(name).description)
        fields = [f.name for f in dataclasses.fields(settings_class)]
        add_dataclass_arguments(group, settings_class, skip=tuple(f for f in fields if f in seen))
        seen.update(fields)
    switches = parser.add_argument_group("method switches", "older spellings of --method")
    switches.add_argument("--mip-splatting", dest="mip_splatting", action="store_true", help="same as --method mip-splatting")
    switches.add_argument("--dropout-gs", dest="dropout_gs", action="store_true", help="same as --method dropout-gs")
    parser.add_argument("--config", dest="config_file", type=Path, default=None,
                        help="read settings from a JSON file (flags given here override it)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _method_flags_given(args: argparse.Namespace, settings_class: type) -> bool:
    return any(getattr(args, f.name, None) is not None for f in dataclasses.fields(settings_class))


def _chosen_method(args: argparse.Namespace, base_method: str) -> str:
    """--method, else an older switch, else the method whose flags were given, else ``base_method``."""
    from ..errors import ConfigError

    switched = [method for switch, method in _METHOD_SWITCHES.items() if getattr(args, switch, False)]
    if getattr(args, "esgs", False):
        switched.append("esgs")
    if args.method is not None:
        switched = [args.method, *[m for m in switched if m != args.method]]
    if len(set(switched)) > 1:
        raise ConfigError(f"one method per run, got {', '.join(switched)}", hint="choose one with --method NAME")
    if switched:
        return switched[0]
    if base_method != "3dgs":
        return base_method
    flagged = [name for name, cls in _settings_classes().items() if _method_flags_given(args, cls)]
    if len(flagged) > 1:
        raise ConfigError(f"flags of several methods were given ({', '.join(flagged)})",
                          hint="choose one with --method NAME")
    return flagged[0] if flagged else "3dgs"


def build_config(args: argparse.Namespace):
    """The TrainConfig of a command line: a resumed run's config.json (or --config), then flags.

    The method is ``--method`` (``--mip-splatting`` / ``--dropout-gs`` too), else the saved
    or --config file's, else the one whose flags were given. ``--esgs`` or ``--method esgs``
    given explicitly starts from :func:`~esgs.core.methods.full_esgs` for ``--priors`` (default
    ``auto``); ESGS flags alone start from every part off, as before methods were registered.
    """
    from ..config import config_to_dict, dataclass_from_args
    from ..errors import ConfigError
    from ..methods import full_esgs, get_method, load_run_config, train_config_from_dict
    from ..train.config import TrainConfig
    from ..formats.run_dir import RunDir

    if args.scene is None:
        raise ConfigError("the scene folder is required", hint="esgs train SCENE --out RUN_DIR")
    if args.out is None:
        raise ConfigError("--out is required", hint="esgs train SCENE --out RUN_DIR")
    base = None
    if args.resume and RunDir(args.out).config.is_file():
        # a resumed run keeps the settings it was started with; flags override the safe ones
        base = load_run_config(RunDir(args.out).config)
    elif args.config_file is not None:
        import json

        try:
            data = json.loads(Path(args.config_file).read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            raise ConfigError(f"cannot read the settings file: {err}", path=args.config_file) from err
        base = train_config_from_dict(data, source=args.config_file, saved=False)
    config = dataclass_from_args(TrainConfig, args, base=base)
    name = _chosen_method(args, base.method if base is not None else "3dgs")
    method = get_method(name)
    if base is not None and base.method == name:
        settings = base.method_config
    elif name == "esgs" and (args.method == "esgs" or getattr(args, "esgs", False)):
        settings = full_esgs(getattr(args, "priors", None) or "auto", scene=Path(args.scene))
    else:
        settings = method.default_settings()
    if method.settings_class is not None:
        settings = dataclass_from_args(method.settings_class, args, base=settings)
    if getattr(args, "vanilla", False):
        from ..train.config import SKY_MODEL_SETTINGS, VANILLA_3DGS, vanilla

        if base is not None and args.resume and any(getattr(base, key) != value for key, value in VANILLA_3DGS.items()):
            raise ConfigError("--vanilla cannot change a run that is being resumed: it keeps the settings it started with",
                              path=args.out, hint="drop --vanilla, or start a new run in another --out folder")
        clashing = [key for key, value in VANILLA_3DGS.items()
                    if getattr(args, key, None) is not None and getattr(args, key) != value]
        # settings of the sky model that --vanilla turns off: giving them would do nothing
        clashing += [key for key in SKY_MODEL_SETTINGS if getattr(args, key, None) is not None]
        if clashing:
            raise ConfigError(f"--vanilla sets {', '.join('--' + key.replace('_', '-') for key in clashing)} itself "
                              "or turns it off", hint="leave those flags out, or drop --vanilla")
        config = vanilla(config)
    values = {**config_to_dict(config), "scene": str(args.scene), "method": name,
              "method_config": config_to_dict(settings) if settings is not None else None}
    return train_config_from_dict(values, saved=False)


def run(args: argparse.Namespace) -> int:
    from ..methods import get_method, method_names, train
    from ..progress import ConsoleProgress

    if args.list_methods:
        for name in method_names():
            method = get_method(name)
            print(f"{name:15s} {method.label}: {method.description}")
        return 0
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
