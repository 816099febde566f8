"""Regenerate docs/walkthrough.md by running its commands, or check that it is current.

The walkthrough is Markdown in which every ```bash block is run, in order, in one empty
folder, and the ```text or ```json block right after it (blank lines between them only) is
replaced by what the commands printed (stdout and stderr, lines cut at 100 characters; a
command ending in ``# (first N lines)`` keeps its first N lines). A ```python block announced
by a line ```NAME.py`:`` is written to that file before any command runs.

    python docs/generate_walkthrough.py            # rewrite docs/walkthrough.md (atomically)
    python docs/generate_walkthrough.py --check    # exit 1 if a quoted figure moved by more
                                                   # than the tolerance (default 2 %)
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

WALKTHROUGH = Path(__file__).with_name("walkthrough.md")
BLOCK = re.compile(r"```(\w+)\n(.*?)```", re.S)
FILE_LABEL = re.compile(r"`([\w.-]+\.py)`:\s*$")
FIRST_LINES = re.compile(r"#\s*\(first (\d+) lines\)\s*$")
NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?")
WIDTH = 100


def _run(command: str, cwd: Path) -> str:
    env = {**os.environ, "TQDM_DISABLE": "1", "COLUMNS": "100"}
    r = subprocess.run(["bash", "-c", command], cwd=cwd, env=env, stdout=subprocess.PIPE,
                       stderr=subprocess.STDOUT, text=True, timeout=900)
    text = r.stdout.rstrip("\n")           # results and progress, in the order they came
    m = FIRST_LINES.search(command)
    lines = text.splitlines()
    if m:
        lines = lines[:int(m.group(1))]
    return "\n".join(line if len(line) <= WIDTH else line[:WIDTH - 4] + " ..." for line in lines)


def regenerate(text: str, cwd: Path, progress=print) -> str:
    """The walkthrough with every output block replaced by what its commands print now."""
    for m in BLOCK.finditer(text):                  # the scripts the commands run, first
        label = text[:m.start()].rstrip().rsplit("\n", 1)[-1]
        f = FILE_LABEL.search(label)
        if m.group(1) == "python" and f:
            (cwd / f.group(1)).write_text(m.group(2))
    out, pos = [], 0
    pending: str | None = None          # output of the last bash block, not yet placed
    for m in BLOCK.finditer(text):
        lang, body = m.group(1), m.group(2)
        between = text[pos:m.start()]
        out.append(between)
        if lang == "bash":
            commands = [c for c in body.splitlines() if c.strip() and not c.startswith("#")]
            outputs = []
            for c in commands:
                progress(f"$ {c}")
                outputs.append(_run(c, cwd))
            pending = "\n".join(o for o in outputs if o)
            out.append(m.group(0))
        elif lang in ("text", "json") and pending is not None and not between.strip():
            out.append(f"```{lang}\n{pending}\n```")
            pending = None
        else:
            out.append(m.group(0))
            pending = None
        pos = m.end()
    out.append(text[pos:])
    return "".join(out)


ELAPSED = re.compile(r"\[\s*[\d.]+ s\]")      # the demo's elapsed-time stamps: not figures


def _figures(text: str) -> list[list[tuple[float, float]]]:
    """Each output block's figures as (value, one unit of its last printed digit)."""
    def unit(x: str) -> float:
        mantissa = x.lower().split("e")[0]
        decimals = len(mantissa.split(".")[1]) if "." in mantissa else 0
        exponent = int(x.lower().split("e")[1]) if "e" in x.lower() else 0
        return 10.0 ** (exponent - decimals)
    return [[(float(x), unit(x)) for x in NUMBER.findall(ELAPSED.sub("", body))]
            for lang, body in BLOCK.findall(text) if lang in ("text", "json")]


def moved_figures(old: str, new: str, rel_tol: float) -> list[str]:
    """Quoted figures that moved by more than ``rel_tol`` (relative), with an absolute floor of
    0.05 or one unit of the figure's last printed digit, whichever is larger (a figure printed
    to 0.1 flips by 0.1 where its value sits on a rounding boundary)."""
    problems = []
    a, b = _figures(old), _figures(new)
    if len(a) != len(b):
        return [f"{len(a)} output blocks in the file, {len(b)} now"]
    for k, (x, y) in enumerate(zip(a, b)):
        if len(x) != len(y):
            problems.append(f"output block {k + 1}: {len(x)} figures in the file, {len(y)} now")
            continue
        for (u, du), (v, dv) in zip(x, y):
            if abs(u - v) > max(rel_tol * max(abs(u), abs(v)), 0.05, du, dv) * (1 + 1e-9):
                problems.append(f"output block {k + 1}: {u:g} in the file, {v:g} now")
    return problems


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true",
                   help="do not write; exit 1 if a quoted figure moved beyond the tolerance")
    p.add_argument("--rel-tol", type=float, default=0.02,
                   help="relative tolerance of --check (default 0.02)")
    args = p.parse_args(argv)
    old = WALKTHROUGH.read_text()
    with tempfile.TemporaryDirectory(prefix="walkthrough-") as tmp:
        new = regenerate(old, Path(tmp), progress=lambda s: print(s, file=sys.stderr))
    if args.check:
        problems = moved_figures(old, new, args.rel_tol)
        for line in problems:
            print(line)
        return 1 if problems else 0
    tmp = WALKTHROUGH.with_suffix(".md.tmp")
    tmp.write_text(new)
    os.replace(tmp, WALKTHROUGH)
    return 0


if __name__ == "__main__":
    sys.exit(main())
