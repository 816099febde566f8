"""Fuzzing the files a laboratory hands to deltatwin: scenarios, datasets (CSV, its JSON sidecar,
Parquet), model files (the fitted physics TOML, the stepwise JSON), ports files and setup files.

Each target starts from a valid file written by the project's own writers (or shipped with it);
a seeded ``numpy.random.Generator`` draws mutations of it: keys dropped, duplicated, retyped or
added; numbers out of range, non-finite or huge; truncation at every table (or row) boundary and
mid-line; wrong encodings; an empty file; a folder in its place. Each mutated file goes through
the public reader (and, when accepted, the use a command makes of it) and its outcome is
classified as a command line would end (deltatwin/cli.py: ``BAD_INPUT_ERRORS`` exit 2):

  ``clean``     refused with a bad-input error whose message names the file (and the key or
                column the mutation touched);
  ``vague``     refused with a bad-input error that does not name them;
  ``accepted``  read and used (a mutation that may leave the file valid);
  ``silent``    read and used although the mutation certainly made the input invalid;
  ``traceback`` any other exception;
  ``hang``      still running after ``timeout_s`` (an interval timer interrupts it).

The reusable parts: ``targets(folder)`` (the valid base files), ``cases(target, rng)`` and
``run(case)``; tests/test_fuzz_inputs.py runs a sample, benchmarks/fuzz_inputs.py every case.
"""
from __future__ import annotations

import copy
import io
import json
import math
import re
import resource
import shutil
import signal
import tomllib
from collections import Counter
from collections.abc import Callable
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import tomli_w

from deltatwin.cli import BAD_INPUT_ERRORS

OUTCOMES = ("clean", "vague", "accepted", "silent", "traceback", "hang")
HUGE_STRING = "x" * 1_000_000


def default_rule(kind: str, path: tuple) -> bool:
    """Whether a mutation of ``kind`` at ``path`` certainly makes a hand-written file invalid:
    a wrong type or a non-finite or huge number always; a dropped or added key, a zero, a
    negation, an empty value, a cut at a table boundary or mid-line may leave it valid."""
    return kind in ("retype", "nonfinite", "huge", "encoding", "file", "duplicate")


def checksummed_rule(kind: str, path: tuple) -> bool:
    """A file deltatwin wrote with its content's checksum: every change is damage."""
    return True


@dataclass
class Target:
    """A valid base file, how to read it (``read(path)`` raises or returns; it also makes the
    use a command makes of the result) and which mutations certainly invalidate it
    (``invalid(kind, path)``)."""
    name: str
    base: Path
    kind: str                            # "toml", "json", "csv", "parquet"
    read: Callable[[Path], object]
    invalid: Callable[[str, tuple], bool] = default_rule
    # an error must name the key or column touched (False: a checksum refuses the file whole)
    names_keys: bool = True
    leaf_filter: Callable[[tuple], bool] = lambda path: True
    # the file names an error may give (default: the file's own)
    named: tuple[str, ...] = ()


@dataclass
class Case:
    target: Target
    name: str
    invalid: bool                        # the mutation certainly makes the input invalid
    make: Callable[[Path], Path]         # writes the mutated input in a folder; -> path to read
    names: tuple[str, ...] = ()          # words the error must contain besides the file name
    whole_file: bool = False             # a change of the file as a whole (cut, encoding, ...)


@dataclass
class Result:
    case: Case
    outcome: str
    detail: str = ""


@dataclass
class Report:
    results: list[Result] = field(default_factory=list)

    def counts(self, target: str | None = None) -> Counter:
        return Counter(r.outcome for r in self.results
                       if target is None or r.case.target.name == target)

    def faults(self) -> list[Result]:
        return [r for r in self.results if r.outcome not in ("clean", "accepted")]

    def faults_text(self) -> str:
        return "\n".join(f"  {r.case.target.name}: {r.outcome}: {r.case.name}: {r.detail}"
                         for r in self.faults())

    def table(self) -> str:
        names = sorted({r.case.target.name for r in self.results})
        rows = [f"{'target':<16}{'cases':>6}" + "".join(f"{o:>10}" for o in OUTCOMES)]
        for n in [*names, None]:
            c = self.counts(n)
            rows.append(f"{n or 'all':<16}{sum(c.values()):>6}"
                        + "".join(f"{c[o]:>10}" for o in OUTCOMES))
        return "\n".join(rows)


# --------------------------------------------------------------------------- running one case

class Hang(BaseException):
    """Raised by the interval timer in a case that ran past its time limit (a BaseException, so
    that no ``except Exception`` in the code under test swallows it)."""


@contextmanager
def _limits(timeout_s: float, memory_bytes: int):
    """A time limit (SIGALRM interval timer -> Hang) and an address-space limit (an attempt to
    allocate terabytes becomes a MemoryError, counted as a traceback, not a dead machine)."""
    def on_alarm(signum, frame):
        raise Hang()

    old_handler = signal.signal(signal.SIGALRM, on_alarm)
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with open("/proc/self/statm") as f:
        in_use = int(f.read().split()[0]) * resource.getpagesize()
    limit = in_use + memory_bytes
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    signal.setitimer(signal.ITIMER_REAL, timeout_s)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
        signal.signal(signal.SIGALRM, old_handler)


def run(case: Case, folder: Path, timeout_s: float = 20.0,
        memory_bytes: int = 4 << 30) -> Result:
    folder.mkdir(parents=True, exist_ok=True)
    path = case.make(folder)
    named = case.target.named or (path.name,)
    try:
        with _limits(timeout_s, memory_bytes):
            case.target.read(path)
    except Hang:
        return Result(case, "hang", f"still running after {timeout_s:g} s")
    except BAD_INPUT_ERRORS as exc:
        text = str(exc)
        missing = [w for w in case.names if w not in text]
        if not any(n in text for n in named):
            missing.append(" or ".join(named))
        if missing:
            return Result(case, "vague", f"{type(exc).__name__}: {text[:300]} (does not name "
                                         f"{missing})")
        return Result(case, "clean", text[:300])
    except Exception as exc:                                  # noqa: BLE001 - counted
        return Result(case, "traceback", f"{type(exc).__name__}: {str(exc)[:300]}")
    return Result(case, "silent" if case.invalid else "accepted")


def fuzz(targets: list[Target], rng: np.random.Generator, folder: Path,
         per_target: int | None = None, timeout_s: float = 20.0) -> Report:
    """Every case of every target, or with ``per_target`` every whole-file case (cuts,
    encodings, empty, a folder) and ``per_target`` key, value and column cases drawn by
    ``rng``."""
    report = Report()
    for t in targets:
        all_cases = cases(t, rng)
        keys = [c for c in all_cases if not c.whole_file]
        if per_target is not None and per_target < len(keys):
            keep = set(rng.choice(len(keys), size=per_target, replace=False).tolist())
            all_cases = [c for c in all_cases if c.whole_file] + [
                c for i, c in enumerate(keys) if i in keep]
        for k, case in enumerate(all_cases):
            report.results.append(run(case, folder / t.name / f"{k:04d}", timeout_s))
    return report


# --------------------------------------------------------------------------- mutations

def _walk(doc, prefix=()):
    """(path, value) of every leaf and every table of a parsed document (paths of keys and list
    indices), tables before their contents."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield (*prefix, k), v
            yield from _walk(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            if isinstance(v, (dict, list)):
                yield (*prefix, i), v
                yield from _walk(v, (*prefix, i))


def _key_of(path: tuple) -> str:
    """The last key name of a path (a list index names its list)."""
    return next(str(p) for p in reversed(path) if isinstance(p, str))


def _set(doc, path, value):
    out = copy.deepcopy(doc)
    node = out
    for p in path[:-1]:
        node = node[p]
    node[path[-1]] = value
    return out


def _drop(doc, path):
    out = copy.deepcopy(doc)
    node = out
    for p in path[:-1]:
        node = node[p]
    del node[path[-1]]
    return out


def _value_mutations(value, rng) -> list[tuple[str, object, str]]:
    """(label, new value, kind) for one leaf; kind: retype, nonfinite, huge, range."""
    if isinstance(value, bool):
        return [("as text", "yes", "retype"), ("as 1", 1, "retype")]
    if isinstance(value, (int, float)):
        out = [("as text", str(value), "retype"), ("as a list", [value], "retype"),
               ("nan", math.nan, "nonfinite"), ("inf", math.inf, "nonfinite"),
               ("-inf", -math.inf, "nonfinite"), ("1e300", 1e300, "huge"),
               ("-1e300", -1e300, "huge"), ("zero", 0 if isinstance(value, int) else 0.0,
                                            "range"),
               ("negated", -value if value else -1, "range")]
        if isinstance(value, int):
            out += [("10^18", 10**18, "huge"), ("fraction", value + 0.5, "retype")]
        return out
    if isinstance(value, str):
        return [("as a number", 1, "retype"), ("as a list", [value], "retype"),
                ("empty", "", "range"), ("1 MB", HUGE_STRING, "range"),
                ("control characters", value + "\x00\x1b", "range")]
    if isinstance(value, list):
        out = [("empty list", [], "range"), ("as a scalar", 1.5, "retype")]
        if value:
            out += [("element as a table", [{"k": 1}] + value[1:], "retype"),
                    ("element repeated", value + value[:1], "range")]
        return out
    if isinstance(value, dict):
        return [("as a scalar", 1.5, "retype")]
    return []


def _write_doc(target: Target, doc) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        path = folder / target.base.name
        if target.kind == "toml":
            path.write_text(tomli_w.dumps(doc))
        else:
            path.write_text(json.dumps(doc, indent=1))
        _companions(target, folder)
        return path
    return make


def _write_bytes(target: Target, data: bytes) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        path = folder / target.base.name
        path.write_bytes(data)
        _companions(target, folder)
        return path
    return make


def _companions(target: Target, folder: Path) -> None:
    """Files that travel with the base (a CSV's sidecar, a sidecar's CSV)."""
    for f in target.base.parent.iterdir():
        if f.is_file() and f.name != target.base.name and not (folder / f.name).exists():
            shutil.copy(f, folder / f.name)


def _document_cases(t: Target, doc, rng) -> list[Case]:
    out = []

    def case(name, kind, path, new_doc, key):
        invalid = t.invalid(kind, path)
        out.append(Case(t, name, invalid, _write_doc(t, new_doc),
                        (key,) if invalid and t.names_keys else ()))

    for path, value in _walk(doc):
        if not t.leaf_filter(path):
            continue
        key = _key_of(path)
        where = ".".join(map(str, path))
        if isinstance(path[-1], str):
            case(f"drop {where}", "drop", path, _drop(doc, path), key)
        for label, new, kind in _value_mutations(value, rng):
            if new == value and type(new) is type(value):
                continue                                  # no change (an empty list emptied)
            case(f"{where} {label}", kind, path, _set(doc, path, new), key)
        if isinstance(value, dict):
            unknown = f"zz_unknown_{int(rng.integers(1000))}"
            case(f"{where} + unknown key", "unknown", path, _set(doc, (*path, unknown), 1.0),
                 unknown)
    return out


def _text_cases(t: Target, text: str, rng) -> list[Case]:
    """Truncation at every table boundary (TOML) or every line (JSON, a few drawn), mid-line,
    a key line duplicated, wrong encodings."""
    lines = text.splitlines(keepends=True)
    starts = np.cumsum([0] + [len(x) for x in lines])
    out = []
    if t.kind == "toml":
        bounds = [i for i, x in enumerate(lines) if x.startswith("[") and i > 0]
    else:
        bounds = sorted(rng.choice(np.arange(1, len(lines)), size=min(8, len(lines) - 1),
                                   replace=False).tolist())
    for i in bounds:
        out.append(Case(t, f"cut before line {i + 1}", t.invalid("truncate", ()) or t.kind == "json",
                        _write_bytes(t, text[:starts[i]].encode())))
        j = int(rng.integers(max(0, i - 3), i)) if i else 0     # a line of the table before
        cut = int(starts[j] + rng.integers(1, max(2, len(lines[j].rstrip("\n")))))
        out.append(Case(t, f"cut mid-line {j + 1}", t.invalid("midline", ()) or t.kind == "json",
                        _write_bytes(t, text[:cut].encode())))
    keyed = [i for i, x in enumerate(lines) if re.match(r"\s*[\w\"]+\s*[=:]", x)]
    if t.kind == "toml" and keyed:
        i = int(rng.choice(keyed))
        dup = "".join(lines[:i + 1] + [lines[i]] + lines[i + 1:])
        out.append(Case(t, f"line {i + 1} duplicated", True, _write_bytes(t, dup.encode()),
                        ("line",) if t.names_keys else ()))
    pos = int(rng.integers(0, len(text)))
    out += [Case(t, "UTF-16", True, _write_bytes(t, text.encode("utf-16"))),
            Case(t, "UTF-8 with a byte-order mark", t.invalid("bom", ()),
                 _write_bytes(t, b"\xef\xbb\xbf" + text.encode())),
            Case(t, f"byte 0xFF at {pos}", True,
                 _write_bytes(t, text[:pos].encode() + b"\xff" + text[pos:].encode()))]
    return out


def _file_cases(t: Target) -> list[Case]:
    def folder_instead(folder: Path) -> Path:
        path = folder / t.base.name
        path.mkdir()
        _companions(t, folder)
        return path
    return [Case(t, "empty file", True, _write_bytes(t, b"")),
            Case(t, "blank lines", True, _write_bytes(t, b"\n\n")),
            Case(t, "a folder", True, folder_instead)]


def _json_duplicate_key(t: Target, text: str) -> Case:
    """The first key of the top-level object written twice (json.loads keeps the last one)."""
    doc = json.loads(text)
    first = next(iter(doc))
    dup = "{" + json.dumps(first) + ": " + json.dumps(doc[first]) + ", " + text.lstrip()[1:]
    return Case(t, f"key {first!r} twice", True, _write_bytes(t, dup.encode()),
                (first,) if t.names_keys else ())


def _csv_cases(t: Target, rng) -> list[Case]:
    """A laboratory CSV without a sidecar: columns dropped, renamed, repeated; cells retyped,
    non-finite, huge; rows repeated; truncation at every row boundary (drawn) and mid-line."""
    df = pd.read_csv(t.base)
    text = t.base.read_text()
    from deltatwin.twin.dataset import REQUIRED_COLUMNS

    def frame(new: pd.DataFrame) -> Callable[[Path], Path]:
        return _write_bytes(t, new.to_csv(index=False, lineterminator="\n").encode())

    out = []
    numeric = [c for c in df.columns if pd.api.types.is_numeric_dtype(df[c])]

    def case(name, invalid, make, column=None):
        invalid = invalid or t.invalid("cell", ())
        out.append(Case(t, name, invalid, make,
                        (column,) if invalid and column and t.names_keys else ()))

    for c in df.columns:
        case(f"drop column {c}", c in REQUIRED_COLUMNS, frame(df.drop(columns=[c])), c)
        row = int(rng.integers(len(df)))
        # a free-text column (session) may hold any text; split only cal or val
        cells = [("empty", None)] + ([("text", "abc")] if c in numeric or c == "split" else [])
        if c in numeric:
            cells += [("inf", math.inf), ("1e300", 1e300), ("-1e300", -1e300)]
        for label, value in cells:
            new = df.astype({c: object}).copy()
            new.loc[row, c] = value
            optional = label == "empty" and c not in REQUIRED_COLUMNS and c in numeric
            case(f"{c} row {row} {label}", not optional, frame(new), c)
    c = str(rng.choice(numeric))
    case(f"column {c} twice", True, frame(pd.concat([df, df[[c]]], axis=1)), c)
    case("a row repeated", True, frame(pd.concat([df, df.iloc[[int(rng.integers(len(df)))]]])))
    case("header only", True, frame(df.iloc[:0]))
    lines = text.splitlines(keepends=True)
    starts = np.cumsum([0] + [len(x) for x in lines])
    for i in sorted(rng.choice(np.arange(2, len(lines)), size=min(6, len(lines) - 2),
                               replace=False).tolist()):
        out.append(Case(t, f"cut before row {i}", t.invalid("truncate", ()),
                        _write_bytes(t, text[:starts[i]].encode())))
        cut = int(starts[i] + rng.integers(1, len(lines[i]) - 1))
        out.append(Case(t, f"cut mid-row {i}", True, _write_bytes(t, text[:cut].encode())))
    pos = int(rng.integers(len(lines[0]), len(text)))
    out += [Case(t, "UTF-16", True, _write_bytes(t, text.encode("utf-16"))),
            Case(t, f"byte 0xFF at {pos}", True,
                 _write_bytes(t, text[:pos].encode() + b"\xff" + text[pos:].encode()))]
    return out


def _parquet_cases(t: Target, rng) -> list[Case]:
    data = t.base.read_bytes()
    cuts = sorted(rng.choice(np.arange(1, len(data)), size=8, replace=False).tolist())
    return [Case(t, f"cut at byte {k}", True, _write_bytes(t, data[:k])) for k in cuts]


def cases(t: Target, rng: np.random.Generator) -> list[Case]:
    """Every mutation of target ``t`` (random choices from ``rng``)."""
    whole = _file_cases(t)
    keyed = []
    if t.kind in ("toml", "json"):
        text = t.base.read_text()
        doc = tomllib.loads(text) if t.kind == "toml" else json.loads(text)
        keyed += _document_cases(t, doc, rng)
        whole += _text_cases(t, text, rng)
        if t.kind == "json":
            whole.append(_json_duplicate_key(t, text))
    elif t.kind == "csv":
        csv_cases = _csv_cases(t, rng)
        whole += [c for c in csv_cases if c.name.startswith(("cut ", "UTF", "byte "))]
        keyed += [c for c in csv_cases if not c.name.startswith(("cut ", "UTF", "byte "))]
    elif t.kind == "parquet":
        whole += _parquet_cases(t, rng)
    for c in whole:
        c.whole_file = True
    return whole + keyed


# --------------------------------------------------------------------------- model files

def _first_number(value, new):
    """``value`` (a number or nested lists of numbers) with its first number replaced."""
    if isinstance(value, list):
        return [_first_number(value[0], new)] + value[1:] if value else value
    return new


def model_file_cases(t: Target) -> list[Case]:
    """Named mutations of a fitted physics model as they happen to one (a hand edit, another
    version, a colleague's file): a misspelled or unknown effect, a user effect's code, other
    format versions, values in another unit (a key's unit suffix, a unit in the value), NaN,
    infinite and huge values, wrong shapes and types, missing sections, misspelled keys. Each
    certainly makes the file invalid and names the key its error must name."""
    doc = tomllib.loads(t.base.read_text())
    effect = doc["model"]["effects"][0]
    param = next(iter(doc["effects"][effect]))
    value = doc["effects"][effect][param]
    unit = param.rsplit("_", 1)[0]
    out = []

    def case(name, new_doc, *names):
        out.append(Case(t, name, True, _write_doc(t, new_doc), names))

    rename = lambda table, old, new: {new if k == old else k: v for k, v in table.items()}
    case("effect misspelled", _set(doc, ("model", "effects"), [effect + "z"]), effect + "z")
    case("effect not in the library", _set(doc, ("model", "effects"), ["warp_drive"]),
         "warp_drive")
    case("a user effect's code", _set(doc, ("model", "effects"), ["./evil.py:Evil"]), "evil.py")
    case("effects as one string", _set(doc, ("model", "effects"), effect), "effects")
    case("an effect's table misspelled", _set(doc, ("effects",), rename(
        doc["effects"], effect, effect[:-1])), effect)
    for v in (3, -1, "2", 2.5, True):
        case(f"format_version {v!r}", _set(doc, ("format_version",), v), "format_version")
    case("another format", _set(doc, ("format",), "deltatwin-stepwise-model"), "format")
    for suffix in ("_mm", "_um", "_nm"):
        case(f"{param} in {suffix[1:]}", _set(doc, ("effects", effect), rename(
            doc["effects"][effect], param, unit + suffix)), unit + suffix)
    case(f"{param} with its unit in the value", _set(doc, ("effects", effect, param), "5 nm"),
         param)
    for label, x in (("NaN", math.nan), ("inf", math.inf), ("-inf", -math.inf),
                     ("1e300", 1e300), ("text", "0.0")):
        case(f"{param} {label}", _set(doc, ("effects", effect, param), _first_number(value, x)),
             param)
    case(f"{param} one element short", _set(doc, ("effects", effect, param),
                                             value[:-1] if isinstance(value, list) else [value]),
         param)
    case(f"{param} misspelled", _set(doc, ("effects", effect),
                                     rename(doc["effects"][effect], param, param + "s")),
         param + "s")
    for key, bad in (("noise_nm", math.nan), ("noise_nm", -5.0), ("noise_nm", "5"),
                     ("identifiable_ratio", math.inf), ("data_sha256", "abc"),
                     ("code_sha256", 5), ("data", 1.0)):
        case(f"[model] {key} = {bad!r}", _set(doc, ("model", key), bad), key)
    case("[model] noise in um", _set(doc, ("model",), rename(doc["model"], "noise_nm",
                                                             "noise_um")), "noise_um")
    case("[model.sensors] a part as a number",
         _set(doc, ("model", "sensors"), {"base": 3}), "sensors")
    case("no [model]", _drop(doc, ("model",)), "model")
    case("no [effects]", _drop(doc, ("effects",)), effect)
    case(f"no [effects.{effect}]", _drop(doc, ("effects", effect)), effect)
    case("a misspelled table [knwon]", _set(doc, ("knwon",), {}), "knwon")
    if "identification" in doc:
        ident = doc["identification"]
        case("[identification] parameters reversed", _set(
            doc, ("identification", "parameters"), ident["parameters"][::-1]), "identification")
        case("[identification] a direction with NaN", _set(
            doc, ("identification", "directions"),
            [_first_number(ident["directions"][0], math.nan)] + ident["directions"][1:]),
             "identification")
    case("[fit] n_parameters -1", _set(doc, ("fit", "n_parameters"), -1), "n_parameters")
    case("[fit] val_err90_nm as text", _set(doc, ("fit", "val_err90_nm"), "small"),
         "val_err90_nm")
    return out


def cli_reader(argv: list[str]) -> Callable[[Path], None]:
    """A ``read`` for ``run``: the command line ``argv`` ('{model}' replaced by the file) through
    ``deltatwin.cli.main`` in this process, as a user runs it. Exit 2 with exactly one error
    line: that line raised as a bad-input error (``run`` checks it names the file and key);
    exit 0: accepted; anything else (another exit code, several error lines, a traceback, an
    exception out of main) is a fault."""
    def read(path: Path) -> None:
        from deltatwin.cli import UserError, main

        err = io.StringIO()
        with redirect_stderr(err), redirect_stdout(io.StringIO()):
            code = main([a.replace("{model}", str(path)) for a in argv])
        text = err.getvalue()
        errors = [x for x in text.splitlines() if ": error: " in x]
        if code == 0:
            return
        if code == 2 and len(errors) == 1 and "Traceback" not in text:
            raise UserError(errors[0])
        raise RuntimeError(f"exit {code}, {len(errors)} error lines: {text[-300:]!r}")
    return read


# --------------------------------------------------------------------------- the targets

def _read_scenario(path: Path):
    from deltatwin.twin.scenario import Scenario
    Scenario.load(path).simulate(scale=0.02)


def _read_dataset(path: Path):
    from deltatwin.twin.dataset import read_dataset
    read_dataset(path)


def _read_ports(path: Path):
    from deltatwin.hw.lab import open_lab
    from deltatwin.hw.ports import load_ports
    open_lab(load_ports(path)).close()          # drivers made (ports open at first use)


def _reader_of_model(data: Path):
    def read(path: Path):
        from deltatwin.calibration.diagnosis.compare import evaluate, load_model_file
        from deltatwin.twin.dataset import read_dataset
        model = load_model_file(path) if path.suffix == ".toml" else None
        df, meta = read_dataset(data)
        if model is not None:
            evaluate(df, meta, model)                          # compare's use of it
        else:
            from deltatwin.calibration.blackbox.model_file import load_model
            load_model(path).predict(df)                       # calibrate --model's use
    return read


def _example_ports():
    from deltatwin.hw.ports import LabPorts, Port
    from deltatwin.hw.retry import RetryPolicy
    p = Port("/dev/ttyUSB0", 115200, "LF", 1.0)
    return LabPorts(lab="fuzz lab", robot=p, interferometers=Port("/dev/ttyUSB1", 115200, "LF", 2.0),
                    interferometer_axes=("x", "y"),
                    autocollimators=((Port("/dev/ttyUSB2", 9600, "CR", 1.0),
                                      {1: "ac1_ry", 2: "ac1_rz"}),),
                    thermometers=Port("/dev/ttyUSB3", 19200, "LF", 5.0),
                    thermometer_channels={101: "air_x", 102: "base"},
                    clock=Port("/dev/ttyUSB4", 115200, "LF", 2.0),
                    coils=Port("/dev/ttyUSB5", 9600, "LF", 1.0, xonxoff=True),
                    retry=RetryPolicy(), autocollimator_max_step_arcsec=(200.0,))


def targets(folder: Path) -> list[Target]:
    """The valid base files, written by the project's own writers into ``folder``: the shipped
    paper-force scenario; a reduced simulated paper-force campaign (CSV + sidecar, Parquet, and
    a laboratory CSV without sidecar); the physics model and the stepwise direct IGM fitted to
    it by the commands; a ports file; the documented laboratory setup file."""
    from deltatwin.calibration.blackbox.direct_igm import DirectIGM
    from deltatwin.calibration.physics.fit import PhysicsFit
    from deltatwin.calibration.physics.model_file import fitted_toml
    from deltatwin.hw.ports import write_ports
    from deltatwin.twin.dataset import write_dataset
    from deltatwin.twin.scenario import SCENARIO_DIR, Scenario

    folder = Path(folder)
    dirs = {n: folder / n for n in ("scenario", "sidecar", "csv", "lab_csv", "parquet",
                                    "physics", "edited", "stepwise", "ports", "setup",
                                    "with_setup")}
    for d in dirs.values():
        d.mkdir(parents=True, exist_ok=True)
    shutil.copy(SCENARIO_DIR / "paper-force.toml", dirs["scenario"] / "paper-force.toml")
    df, meta = Scenario.load("paper-force").simulate(scale=0.1)
    write_dataset(df, meta, dirs["csv"] / "force.csv")
    write_dataset(df, meta, dirs["sidecar"] / "force.csv")
    write_dataset(df, meta, dirs["parquet"] / "force.parquet")
    df.to_csv(dirs["lab_csv"] / "lab.csv", index=False)
    data = dirs["csv"] / "force.csv"
    fit = PhysicsFit(["geometric_errors"]).fit(df, meta)
    (dirs["physics"] / "fitted.toml").write_text(fitted_toml(fit, str(data)))
    DirectIGM().fit(df, meta).save(dirs["stepwise"] / "igm.json")
    # the same fitted file edited by hand (its checksum line removed, as the error asks)
    fitted = (dirs["physics"] / "fitted.toml").read_text()
    (dirs["edited"] / "fitted.toml").write_text(re.sub(r"(?m)^content_sha256 = .*\n", "", fitted))
    write_ports(dirs["ports"] / "ports.toml", _example_ports())
    # the documented laboratory setup file, its sensor map the campaign's thermometers
    setup = tomllib.loads((Path(__file__).resolve().parents[1] / "docs" / "lab-setup.toml")
                          .read_text())
    (dirs["setup"] / "lab-setup.toml").write_text(tomli_w.dumps({**setup,
                                                                 "sensors": meta["sensors"]}))

    sidecar_keys = ("format_version", "units", "sensors", "cosine_dead_path_m", "csv_sha256")

    def scenario_rule(kind, path):     # any seed numpy takes is a seed
        return default_rule(kind, path) and not (kind == "huge" and path[-1] == "seed")

    def sidecar_rule(kind, path):      # the keys the readers use: huge and empty values too
        return default_rule(kind, path) or kind == "range" and path[-1] == "csv_sha256"

    def physics_rule(kind, path):      # without its checksum it is a hand-edited file
        return not (kind == "drop" and path == ("content_sha256",))

    def edited_rule(kind, path):       # the fit's figures are a report (NaN: not evaluated)
        if path[:1] == ("fit",):
            return kind == "retype"
        return default_rule(kind, path) and (kind != "huge" or path[0] == "effects")

    def ports_rule(kind, path):        # where the instruments are, and what they are
        return default_rule(kind, path) or (
            kind == "drop" and (_key_of(path) in ("url", "channels", "axes") or path in (
                ("robot",), ("interferometers",), ("autocollimators",), ("thermometers",))))

    return [
        Target("scenario", dirs["scenario"] / "paper-force.toml", "toml", _read_scenario,
               scenario_rule),
        # a sidecar's errors name the sidecar; only the keys the readers use are mutated
        Target("sidecar", dirs["sidecar"] / "force.meta.json", "json",
               lambda p: _read_dataset(p.with_name("force.csv")), sidecar_rule,
               leaf_filter=lambda path: path[0] in sidecar_keys),
        # a CSV beside its sidecar: the sidecar's checksum makes every change damage
        Target("csv", data, "csv", _read_dataset, checksummed_rule, names_keys=False,
               named=("force.csv", "force.meta.json")),
        Target("lab_csv", dirs["lab_csv"] / "lab.csv", "csv", _read_dataset),
        Target("parquet", dirs["parquet"] / "force.parquet", "parquet", _read_dataset),
        # written by deltatwin fit and calibrate with their content's checksum
        Target("physics_model", dirs["physics"] / "fitted.toml", "toml",
               _reader_of_model(data), physics_rule, names_keys=False),
        Target("physics_edited", dirs["edited"] / "fitted.toml", "toml",
               _reader_of_model(data), edited_rule),
        Target("stepwise_model", dirs["stepwise"] / "igm.json", "json", _reader_of_model(data),
               checksummed_rule, names_keys=False),
        Target("ports", dirs["ports"] / "ports.toml", "toml", _read_ports, ports_rule),
        # put into the campaign's dataset as `deltatwin setup DATA FILE -o OUT` does
        Target("lab_setup", dirs["setup"] / "lab-setup.toml", "toml",
               cli_reader(["setup", str(dirs["parquet"] / "force.parquet"), "{model}", "-o",
                           str(dirs["with_setup"] / "force.parquet")])),
    ]
