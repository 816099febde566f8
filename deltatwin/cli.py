"""The deltatwin command line.

Each command lives in one module of deltatwin/commands/ exposing ``register(subparsers)``,
which only declares the parser (light imports), and the function it runs, which imports what
the command uses. So ``deltatwin --help`` loads no numerical library. Results go to stdout,
progress, warnings and errors to stderr; every ``--json`` prints strict JSON.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys

from deltatwin import __version__

# command modules, in the order --help lists them
COMMAND_MODULES = (
    "deltatwin.commands.demo",
    "deltatwin.commands.model",
    "deltatwin.commands.simulate",
    "deltatwin.commands.setup",
    "deltatwin.commands.calibrate",
    "deltatwin.commands.fit",
    "deltatwin.commands.effect",
    "deltatwin.commands.compare",
    "deltatwin.commands.report",
    "deltatwin.commands.view",
    "deltatwin.commands.emulate",
    "deltatwin.commands.campaign",
    "deltatwin.commands.compensate",
    "deltatwin.commands.iso",
    "deltatwin.commands.sweep",
)

EXIT_DONE = 0
EXIT_BAD_INPUT = 2
EXIT_INSTRUMENT_FAULT = 3
EXIT_INTERRUPTED = 130
EXIT_CODES_HELP = (f"exit codes: {EXIT_DONE} done, {EXIT_BAD_INPUT} bad input (the message names "
                   f"what and where), {EXIT_INSTRUMENT_FAULT} instrument fault, "
                   f"{EXIT_INTERRUPTED} interrupted")


class UserError(Exception):
    """An error caused by the user's input: printed as one clear line, exit code 2."""


# what ends a command with exit 2 and one line naming what and where: ValueError, the library's
# input errors (scenario, dataset, model file, ports file, ...); OSError, a file that cannot be
# read or written (missing, a folder, no space)
BAD_INPUT_ERRORS = (UserError, ValueError, OSError)


def _verbosity_options() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    g = common.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", action="store_true",
                   help="no progress on stderr (results and errors only)")
    g.add_argument("-v", "--verbose", action="store_true",
                   help="more detail on stderr (the library's log at DEBUG level)")
    return common


class _Commands:
    """The subparsers action, handing every command the common options and a description."""

    def __init__(self, action, common: argparse.ArgumentParser):
        self._action = action
        self._common = common

    def add_parser(self, name: str, **kw) -> argparse.ArgumentParser:
        if "help" in kw and "description" not in kw:
            kw["description"] = kw["help"][:1].upper() + kw["help"][1:] + "."
        # descriptions taken from module docstrings: RST literals read as plain text in a terminal
        kw["description"] = kw.get("description", "").replace("``", "")
        kw.setdefault("parents", []).append(self._common)
        kw.setdefault("epilog", EXIT_CODES_HELP)
        return self._action.add_parser(name, **kw)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="deltatwin", epilog=EXIT_CODES_HELP,
        description="Digital twin, synthetic data and calibration for the flexure-hinge Delta "
                    "robot. Run `deltatwin demo` for the main job, `deltatwin COMMAND --help` "
                    "for a command.")
    parser.add_argument("--version", action="version", version=f"deltatwin {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    commands = _Commands(sub, _verbosity_options())
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(commands)
    return parser


def _configure_logging(args) -> None:
    """The library logs (``logging``); the command line shows INFO and above on stderr."""
    level = (logging.WARNING if getattr(args, "quiet", False) else
             logging.DEBUG if getattr(args, "verbose", False) else logging.INFO)
    from deltatwin.progress import ProgressHandler

    handler = ProgressHandler(sys.stderr)      # progress: one updating line, or plain lines
    handler.setFormatter(logging.Formatter("%(message)s"))
    log = logging.getLogger("deltatwin")
    log.handlers[:] = [handler]
    log.setLevel(level)           # records still propagate: a host's own handlers see them too


def _check_outputs(args) -> None:
    """Every command's output (``-o FILE``, ``--out FOLDER``) is checked before it computes."""
    from deltatwin.files import check_writable

    if getattr(args, "output", None):
        check_writable(args.output)
    if getattr(args, "out", None):
        check_writable(args.out, folder=True)


def _is_instrument_fault(exc: BaseException) -> bool:
    interface = sys.modules.get("deltatwin.twin.instruments.interface")
    return interface is not None and isinstance(exc, interface.InstrumentError)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _configure_logging(args)
    try:
        from deltatwin.threads import set_threads

        set_threads()                 # once, before computing (docs/performance.md)
        _check_outputs(args)
        return int(args.func(args) or EXIT_DONE)
    except KeyboardInterrupt:
        print(f"deltatwin {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:
        if _is_instrument_fault(exc):
            print(f"deltatwin {args.command}: instrument fault: {exc}", file=sys.stderr)
            return EXIT_INSTRUMENT_FAULT
        if isinstance(exc, BAD_INPUT_ERRORS):
            print(f"deltatwin {args.command}: error: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        raise


if __name__ == "__main__":
    sys.exit(main())
