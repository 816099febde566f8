"""Command-line conventions: --version and python -m, a help line for every command and option,
--help fast (no numerical library imported), strict JSON, exit codes."""
import argparse
import json
import subprocess
import sys

import pytest

from deltatwin import __version__
from deltatwin.cli import EXIT_BAD_INPUT, build_parser, main


def _subparsers(parser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            yield from action.choices.items()


def _all_parsers(parser, prefix="deltatwin"):
    yield prefix, parser
    for name, sub in _subparsers(parser):
        yield from _all_parsers(sub, f"{prefix} {name}")


def test_every_command_and_option_has_help():
    missing = []
    for name, parser in _all_parsers(build_parser()):
        if not parser.description:
            missing.append(f"{name}: no description")
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            if not action.help:
                missing.append(f"{name} {'/'.join(action.option_strings) or action.dest}")
        text = parser.format_help()
        assert "``" not in text, f"{name}: RST markup in the help"
    assert not missing, "without help: " + ", ".join(missing)


def test_version_and_python_dash_m():
    r = subprocess.run([sys.executable, "-m", "deltatwin", "--version"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == f"deltatwin {__version__}"


def test_help_imports_no_numerical_library():
    code = ("import sys\nfrom deltatwin.cli import build_parser\nbuild_parser().format_help()\n"
            "heavy = [m for m in ('numpy', 'scipy', 'mujoco', 'pandas', 'rerun', 'statsmodels')"
            " if m in sys.modules]\nprint(heavy)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


def test_bad_input_is_one_line_on_stderr_with_exit_2(tmp_path, capsys):
    rc = main(["simulate", str(tmp_path / "nope.toml"), "-o", str(tmp_path / "x.parquet")])
    out, err = capsys.readouterr()
    assert rc == EXIT_BAD_INPUT and out == ""
    assert "nope.toml: no such scenario file" in err and "quiet/gravity-sag" in err
    assert not (tmp_path / "x.parquet").exists()


def test_a_directory_as_scenario_is_bad_input(tmp_path, capsys):
    rc = main(["simulate", str(tmp_path), "-o", str(tmp_path / "x.parquet")])
    assert rc == EXIT_BAD_INPUT and "is a directory" in capsys.readouterr().err


def test_json_is_strict_even_with_non_finite_figures():
    import numpy as np

    from deltatwin.commands.output import strict_json
    text = strict_json({"a": float("inf"), "b": np.float64("nan"), "c": np.arange(2),
                        "d": (np.int64(3),)})
    assert json.loads(text) == {"a": None, "b": None, "c": [0, 1], "d": [3]}
    assert "Infinity" not in text and "NaN" not in text


@pytest.mark.parametrize("argv", [["effects", "--json"], ["model", "info", "--json"]])
def test_json_commands_print_one_strict_json_object(argv):
    r = subprocess.run([sys.executable, "-m", "deltatwin", *argv], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    json.loads(r.stdout, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))


def test_an_unwritable_output_is_refused_before_computing(tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    rc = main(["simulate", "paper-thermal", "-o", str(blocker / "sub" / "x.parquet")])
    err = capsys.readouterr().err
    assert rc == EXIT_BAD_INPUT and "a-file: is a file" in err
    rc = main(["demo", "--out", str(blocker / "demo")])
    assert rc == EXIT_BAD_INPUT and "a-file: is a file" in capsys.readouterr().err
