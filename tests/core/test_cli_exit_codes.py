"""Exit statuses of ``esgs`` (README, "Command line"): 0 success, 1 runtime failure, 2 bad usage."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from esgs.core.cli import EXIT_FAILURE, EXIT_OK, EXIT_USAGE, main
from esgs.core.formats.ply import GaussianPly, write_gaussians_ply


def _ply(path):
    n = 2
    write_gaussians_ply(path, GaussianPly(np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 0, 3)),
                                          np.zeros(n), np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1))))
    return path


def test_the_statuses_are_the_documented_numbers():
    assert (EXIT_OK, EXIT_FAILURE, EXIT_USAGE) == (0, 1, 2)


def test_a_bare_esgs_prints_help_and_succeeds(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: esgs") and "export" in out


def test_success_runtime_failure_and_bad_option_values(tmp_path, capsys):
    ply = _ply(tmp_path / "g.ply")
    assert main(["export", str(ply), "--format", "splat", "--out", str(tmp_path / "g.splat")]) == 0
    # bad or missing data (a DatasetError): a runtime failure
    assert main(["export", str(tmp_path / "missing"), "--format", "splat"]) == 1
    assert "esgs export: error:" in capsys.readouterr().err
    # an option value the command refuses (a ConfigError): bad usage
    assert main(["export", str(ply), "--out", str(ply)]) == 2


def test_argparse_usage_errors_exit_with_2(capsys):
    with pytest.raises(SystemExit) as raised:
        main(["export"])  # the run argument is missing
    assert raised.value.code == 2
    with pytest.raises(SystemExit) as raised:
        main(["export", "x", "--format", "obj"])
    assert raised.value.code == 2 and "invalid choice" in capsys.readouterr().err


def test_the_process_exit_status(tmp_path):
    """The console entry point passes the status to the shell (python -m esgs.core is the same command)."""
    failed = subprocess.run([sys.executable, "-m", "esgs.core", "export", str(tmp_path / "missing")],
                            capture_output=True, text=True, timeout=120)
    assert failed.returncode == 1 and "Traceback" not in failed.stderr
    bare = subprocess.run([sys.executable, "-m", "esgs.core"], capture_output=True, text=True, timeout=120)
    assert bare.returncode == 0 and bare.stdout.startswith("usage: esgs")


def test_a_negative_coordinate_pair_is_a_value_not_an_option():
    from esgs.core.cli import build_parser, join_negative_lists

    # argparse alone: "-90,60" looks like an option, and --site-center "expected one argument"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["scene", "--preset", "cratered_plain", "--site-center", "-90,60"])
    args = build_parser().parse_args(join_negative_lists(["scene", "--preset", "cratered_plain", "--site-center",
                                                          "-90,60", "--pitch-deg", "-5"]))
    assert args.site_center == "-90,60" and args.pitch_deg == -5
    assert join_negative_lists(["--site-center", "-1.5,2e-3", "-v"]) == ["--site-center=-1.5,2e-3", "-v"]
    # left alone: a positive pair, a single negative number, an option after an option, a short option
    for argv in (["--site-center", "90,-60"], ["--pitch-deg", "-30"], ["--a", "--b"], ["-x", "-1,2"],
                 ["--a=1", "-1,2"]):
        assert join_negative_lists(argv) == argv

