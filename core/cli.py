"""The ``esgs`` console command.

Subcommands are the modules of :mod:`esgs.core.commands`; each defines ``HELP`` (one
line), ``add_arguments(parser)`` and ``run(args) -> int``. Heavy imports (torch...) stay
inside ``run`` so ``esgs --help`` is instant.
"""
from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import re
import sys
from typing import Sequence

from . import commands as _commands_package
from .errors import ConfigError, ESGSError

#: Exit statuses of ``esgs`` (README, "Command line"). Argparse's own usage errors exit with 2
#: too; ``esgs train`` stopped on request (SIGTERM, stop file) exits with 143 and can resume.
EXIT_OK = 0
EXIT_FAILURE = 1  # a runtime failure: bad or missing data, a failed run (any other ESGSError)
EXIT_USAGE = 2  # bad usage: argparse errors and ConfigError (an option value out of range, unknown, inconsistent)
EXIT_INTERRUPTED = 130  # Ctrl-C


def _command_modules() -> dict[str, object]:
    modules = {}
    for info in sorted(pkgutil.iter_modules(_commands_package.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{_commands_package.__name__}.{info.name}")
        name = getattr(module, "NAME", info.name.replace("_", "-"))
        modules[name] = module
    return modules


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every subcommand."""
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="esgs",
        description="ESGS for Blender: Martian surface reconstruction with Gaussian splatting.",
    )
    parser.add_argument("--version", action="version", version=f"esgs {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module in _command_modules().items():
        help_text = getattr(module, "HELP", "")
        command_parser = sub.add_parser(name, help=help_text, description=help_text)
        module.add_arguments(command_parser)  # type: ignore[attr-defined]
        command_parser.set_defaults(_run=module.run)  # type: ignore[attr-defined]
    return parser


#: A list of numbers whose first is negative (``-90,60``): argparse takes it for an option, since
#: only a single negative number is recognised as a value.
_NEGATIVE_NUMBER_LIST = re.compile(r"^-\d+(\.\d*)?(e-?\d+)?(,-?\d+(\.\d*)?(e-?\d+)?)+$")


def join_negative_lists(argv: Sequence[str]) -> list[str]:
    """``--option -90,60`` as ``--option=-90,60`` (what argparse needs; ``esgs scene --site-center
    -90,60`` otherwise fails with "expected one argument"). Only a ``--long`` option followed by a
    comma-separated list of numbers that starts negative is joined: no option name looks like that."""
    out: list[str] = []
    for token in argv:
        if out and _NEGATIVE_NUMBER_LIST.match(token) and out[-1].startswith("--") and "=" not in out[-1]:
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``esgs`` command; returns the exit code."""
    # idle OpenMP threads spin by default, which tripled the CPU time of training steps on a
    # busy 2-core machine; set before any command loads torch (a command-line process is ours)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    parser = build_parser()
    args = parser.parse_args(join_negative_lists(sys.argv[1:] if argv is None else argv))
    if not getattr(args, "_run", None):
        parser.print_help()  # a bare ``esgs`` asks what there is: help on stdout, success
        return EXIT_OK
    try:
        return int(args._run(args) or EXIT_OK)
    except ConfigError as err:
        print(f"esgs {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except ESGSError as err:
        print(f"esgs {args.command}: error: {err}", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt:
        print(f"esgs {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
