"""The ``deltatwin`` command line.

Each subcommand lives beside the code it drives, in a module exposing
``register(subparsers)`` that adds its parser and sets ``func`` (args -> exit code).
This file only lists those modules.
"""
from __future__ import annotations

import argparse
import importlib
import sys

# module path of each command group, in the order shown by --help
COMMAND_MODULES = (
    "deltatwin.commands.demo",
    "deltatwin.commands.model",
    "deltatwin.commands.calibrate",
    "deltatwin.commands.fit",
    "deltatwin.commands.compare",
    "deltatwin.commands.simulate",
    "deltatwin.commands.view",
    "deltatwin.commands.emulate",
    "deltatwin.commands.campaign",
)


class UserError(Exception):
    """An error caused by the user's input: printed as one clear line, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="deltatwin", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:  # a command group not written yet
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (UserError, ValueError, FileNotFoundError) as exc:
        print(f"deltatwin {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"deltatwin {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
