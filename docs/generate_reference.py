"""The generated parts of the reference pages, from the code they describe, so they cannot go
stale: each command's usage and option table in docs/reference/COMMAND.md (from the parser
``deltatwin COMMAND --help`` prints) and each library effect's stages and parameter table in
docs/effects.md (from the effect classes ``deltatwin effects`` lists).

A page holds hand-written text and generated blocks between the two markers below; only the
blocks are rewritten. A command without a page gets one (its description, options and exit
codes; write what it does, the files it writes and an example above the block).

    python docs/generate_reference.py            # rewrite the generated blocks
    python docs/generate_reference.py --check    # exit 1 naming every stale or missing block
"""
from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

import numpy as np

DOCS = Path(__file__).resolve().parent
REFERENCE = DOCS / "reference"
EFFECTS_PAGE = DOCS / "effects.md"
WIDTH = 100                        # the width the usage lines are wrapped at
END = "<!-- end of generated block -->"
BLOCK = re.compile(r"<!-- generated from (.+?) by docs/generate_reference\.py: do not edit -->\n"
                   r"(.*?)" + re.escape(END), re.S)


def begin_marker(source: str) -> str:
    return f"<!-- generated from {source} by docs/generate_reference.py: do not edit -->\n"


# -- commands ------------------------------------------------------------------------------------

def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _cell(text) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _default(action: argparse.Action) -> str:
    if action.required:
        return "required"
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
        return "off"
    if action.default in (None, [], argparse.SUPPRESS):
        return "–"
    return f"`{action.default}`"


def _value(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    if action.choices:
        return " \\| ".join(f"`{c}`" for c in action.choices)
    name = action.metavar or (action.dest.upper() if action.option_strings else action.dest)
    return f"`[{name}]`" if action.nargs == "?" else f"`{name}`"


def option_table(parser: argparse.ArgumentParser) -> str:
    rows = ["| option | value | default | meaning |", "|---|---|---|---|"]
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        name = (", ".join(f"`{s}`" for s in action.option_strings) if action.option_strings
                else f"`{action.metavar or action.dest}` (positional)")
        rows.append(f"| {name} | {_value(action)} | {_default(action)} | "
                    f"{_cell(action.help or '')} |")
    return "\n".join(rows)


def _usage_items(usage: str) -> list[str]:
    """The usage line's words, an option group in brackets or braces kept as one item."""
    items, depth = [""], 0
    for ch in usage:
        if ch == " " and depth == 0:
            items.append("")
            continue
        depth += (ch in "[{(") - (ch in "]})")
        items[-1] += ch
    return [item for item in items if item]


def usage(parser: argparse.ArgumentParser) -> str:
    """The usage line wrapped at WIDTH between whole option groups, as argparse wraps it up to
    Python 3.12 (3.13 breaks inside a group): the page is the same whichever Python writes it."""
    one_line = " ".join(parser.format_usage().split())          # the COLUMNS set by the caller
    head, *items = _usage_items(one_line)
    prog = f"{head} {items.pop(0)}"                              # 'usage:' and the program
    for _ in parser.prog.split()[1:]:                        # the subcommand's words
        prog += f" {items.pop(0)}"
    lines, indent = [prog], " " * (len(prog) + 1)
    for item in items:
        if len(lines[-1]) + 1 + len(item) > WIDTH and lines[-1].strip() != "":
            lines.append(indent + item)
        else:
            lines[-1] += " " + item
    return "\n".join(lines)


def command_block(parser: argparse.ArgumentParser) -> str:
    """The usage and options of one command (and of each of its actions)."""
    parts = [f"```text\n{usage(parser)}\n```", "", option_table(parser)]
    for sub in _subcommands(parser).values():
        parts += ["", f"#### `{sub.prog}`", "", _cell(sub.description or ""), "",
                  f"```text\n{usage(sub)}\n```", "", option_table(sub)]
    if parser.epilog:
        parts += ["", _cell(parser.epilog[:1].upper() + parser.epilog[1:]) + "."]
    return "\n".join(parts) + "\n"


def command_blocks() -> dict[str, tuple[str, str, str]]:
    """command -> (source of the block, the block's text, the command's description)."""
    from deltatwin.cli import build_parser

    columns = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100000"       # argparse's usage on one line: usage() wraps it
    try:
        return {name: (f"`deltatwin {name} --help`", command_block(p),
                       _cell(p.description or ""))
                for name, p in _subcommands(build_parser()).items()}
    finally:
        if columns is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = columns


def new_command_page(name: str, source: str, block: str, description: str) -> str:
    return (f"# `deltatwin {name}`\n\n{description}\n\n## Options\n\n{begin_marker(source)}{block}"
            f"{END}\n")


# -- effects -------------------------------------------------------------------------------------

def _number(x) -> str:
    return f"{x:g}"


def _default_value(default) -> str:
    a = np.asarray(default, float)
    if a.ndim == 0:
        return _number(a)
    if np.all(a == a.flat[0]):
        return f"{_number(a.flat[0])} each, shape {'x'.join(map(str, a.shape))}"
    return re.sub(r"\s+", " ", np.array2string(a, separator=", ", formatter={
        "float_kind": _number})).replace("[ ", "[")


def _fit(p) -> str:
    if p.fit_scale is None:
        return "constant"
    start = "" if p.fit_start is None else f", starts at {_default_value(p.fit_start)}"
    return f"free: typical size {_default_value(p.fit_scale)}{start}"


def effect_block(cls) -> str:
    from deltatwin.twin.effects.base import Effect

    hooks = [n for n, v in vars(Effect).items() if not n.startswith("_") and callable(v)
             and not isinstance(v, classmethod) and n not in ("outside_range", "describe")]
    stages = [h for h in hooks if getattr(cls, h) is not getattr(Effect, h)]
    model = cls.model_stages()
    lines = [f"Stages: {', '.join(f'`{s}`' for s in stages)}. In a fitted model: "
             + (f"yes ({', '.join(f'`{s}`' for s in model)})" if model else
                "no (its consequences reach a model through the thermometers, or it is noise)")
             + (". Reads temperatures." if cls.reads_temperatures else "."), "",
             "| parameter | unit | default | in a fit | meaning |", "|---|---|---|---|---|"]
    for p in cls.parameters:
        lower = "" if p.minimum is None else f" (>= {_number(p.minimum)})"
        lines.append(f"| `{p.name}` | {_cell(p.unit)} | {_default_value(p.default)}{lower} | "
                     f"{_fit(p)} | {_cell(p.doc)} |")
    return "\n".join(lines) + "\n"


def effect_blocks() -> dict[str, str]:
    from deltatwin.twin.effects import LIBRARY

    return {f"effect `{name}`": effect_block(cls) for name, cls in LIBRARY.items()}


# -- pages ---------------------------------------------------------------------------------------

def refresh(text: str, blocks: dict[str, str]) -> tuple[str, list[str]]:
    """``text`` with its generated blocks replaced by ``blocks`` (by source), and the sources
    whose block is missing from the page."""
    seen = set()

    def replace(m):
        seen.add(m.group(1))
        if m.group(1) not in blocks:
            return m.group(0)
        return begin_marker(m.group(1)) + blocks[m.group(1)] + END
    return BLOCK.sub(replace, text), sorted(set(blocks) - seen)


def stale_pages(write: bool) -> list[str]:
    """What is stale or missing; with ``write`` it is rewritten (a missing command page made)."""
    problems = []
    pages = {}
    commands = command_blocks()
    for name, (source, block, description) in commands.items():
        path = REFERENCE / f"{name}.md"
        if not path.is_file():
            problems.append(f"{path.relative_to(DOCS.parent)}: missing (the command "
                            f"`deltatwin {name}` has no reference page)")
            pages[path] = (None, new_command_page(name, source, block, description))
            continue
        pages[path] = (path.read_text(), None)
        new, missing = refresh(pages[path][0], {source: block})
        problems += [f"{path.relative_to(DOCS.parent)}: no generated block from {m}"
                     for m in missing]
        pages[path] = (pages[path][0], new)
    for path in sorted(REFERENCE.glob("*.md")):
        if path.stem not in commands and path.stem != "README":
            problems.append(f"{path.relative_to(DOCS.parent)}: no such command")
    old = EFFECTS_PAGE.read_text()
    new, missing = refresh(old, effect_blocks())
    problems += [f"docs/effects.md: no generated block from {m}" for m in missing]
    pages[EFFECTS_PAGE] = (old, new)
    for path, (old, new) in pages.items():
        if old is not None and new != old:
            problems.append(f"{path.relative_to(DOCS.parent)}: generated block out of date")
        if write and new != old:
            path.parent.mkdir(exist_ok=True)
            path.write_text(new)
    return problems


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 naming every stale or missing block")
    args = ap.parse_args(argv)
    problems = stale_pages(write=not args.check)
    for p in problems:
        print(p)
    return 1 if args.check and problems else 0


if __name__ == "__main__":
    sys.exit(main())
