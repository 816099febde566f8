"""Fuzz tests that count outcomes: mutated scenarios, datasets, model files and ports
files (tests/fuzz_inputs.py) through the public readers and the use a command makes of them.
Every outcome must be a clean refusal naming the file (and the key or column) or an acceptance
of a mutation that may leave the file valid: 0 tracebacks, 0 hangs, 0 silent acceptances of
invalid input, 0 vague messages. Here every whole-file case (cuts at every table boundary and
mid-line, encodings, empty, a folder) and a seeded sample of key, value and column cases;
benchmarks/fuzz_inputs.py runs every case (five minutes on one core: the suite keeps to its
ten)."""
import os
import re
import sys

import numpy as np
import pytest

from deltatwin.cli import main
from tests.fuzz_inputs import Report, cases, fuzz, run, targets

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="SIGALRM, RLIMIT_AS: POSIX")


@pytest.fixture(scope="module")
def bases(tmp_path_factory):
    return {t.name: t for t in targets(tmp_path_factory.mktemp("fuzz-bases"))}


def assert_no_fault(report: Report):
    counts = report.counts()
    assert sum(counts[o] for o in ("traceback", "hang", "silent", "vague")) == 0, (
        report.table() + "\n" + report.faults_text())


def test_fuzz_sample_every_target(bases, tmp_path):
    report = fuzz(list(bases.values()), np.random.default_rng(17), tmp_path, per_target=25)
    assert_no_fault(report)
    counts = report.counts()
    assert counts["clean"] > 300 and counts["accepted"] > 0      # both outcomes were exercised
    model_cases = sum(sum(report.counts(n).values())
                      for n in ("physics_model", "physics_edited", "stepwise_model"))
    assert model_cases >= 21                                     # the 21, and more


def test_a_fitted_file_cut_anywhere_is_refused(bases, tmp_path):
    """The issue's case (a fitted TOML cut before [effects.geometric_errors] was used with the
    default parameters) at every table boundary and mid-line, and without its format version."""
    t = bases["physics_model"]
    cut = [c for c in cases(t, np.random.default_rng(1)) if c.name.startswith("cut ")]
    assert any("cut before line" in c.name for c in cut)
    for k, c in enumerate(cut):
        assert run(c, tmp_path / str(k)).outcome == "clean", c.name
    text = t.base.read_text()
    head, _, tail = text.partition("[effects.geometric_errors]")
    (tmp_path / "cut.toml").write_text(head)
    (tmp_path / "noversion.toml").write_text(re.sub(r"(?m)^format_version = .*\n", "", text))
    for name in ("cut.toml", "noversion.toml"):
        with pytest.raises(ValueError, match=f"{name}.*(cut short|does not match)"):
            t.read(tmp_path / name)


@pytest.mark.parametrize("target,argv", [
    ("scenario", ["simulate", "{bad}", "-o", "{out}/d.csv"]),
    ("lab_csv", ["fit", "{bad}", "--effects", "geometric_errors", "-o", "{out}/m.toml"]),
    ("physics_model", ["compare", "{data}", "--model", "{bad}"]),
    ("stepwise_model", ["calibrate", "{data}", "--features", "force", "--model", "{bad}"]),
    ("ports", ["campaign", "{scenario}", "--instruments", "serial", "--ports", "{bad}",
               "-o", "{out}/c.csv"]),
])
def test_the_commands_exit_2_naming_the_file(bases, tmp_path, capsys, target, argv):
    """The readers' refusals reach the user through deltatwin.cli.main as exit 2 with the file
    named (a file cut mid-line, the damage every reader must catch)."""
    t = bases[target]
    text = t.base.read_bytes()
    bad = tmp_path / t.base.name
    bad.write_bytes(text[:len(text) // 2])
    if target == "lab_csv":
        bad.write_bytes(text[:len(text) // 2].rstrip(b"\n"))
    args = [a.format(bad=bad, out=tmp_path, data=bases["csv"].base,
                     scenario=bases["scenario"].base) for a in argv]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert t.base.name in err and "Traceback" not in err, err
    assert not os.path.exists(tmp_path / "d.csv")


MODEL_COMMANDS = {
    "compare": ["compare", "{data}", "--model", "{model}"],
    "diagnose": ["diagnose", "{data}", "--model", "{model}", "--json"],
    "compensate": ["compensate", "paper-force", "--model", "{model}", "--reduced",
                   "--targets", "3", "-o", "{out}/comp.parquet", "--json"],
}


def test_broken_model_files_through_the_commands(bases, tmp_path):
    """At least 50 broken fitted models (named edits: effect names, user code, format versions,
    units, NaN, shapes, types, missing sections, misspelled keys; and the file cut at every
    table and mid-line, re-encoded, emptied, a folder) through compare, diagnose and compensate
    on the command line: every one exit 2 with one error line naming the file and the key,
    nothing written, 0 tracebacks."""
    from dataclasses import replace

    from tests.fuzz_inputs import cli_reader, model_file_cases

    t = bases["physics_edited"]
    written = bases["physics_model"]          # as deltatwin wrote it: every cut is damage
    broken = model_file_cases(t) + [c for c in cases(written, np.random.default_rng(36))
                                    if c.whole_file and c.invalid]
    assert len(broken) >= 50
    report = Report()
    for name, argv in MODEL_COMMANDS.items():
        argv = [a.format(data=bases["csv"].base, out=tmp_path, model="{model}") for a in argv]
        for k, c in enumerate(broken):
            target = replace(c.target, name=name, read=cli_reader(argv))
            report.results.append(run(replace(c, target=target), tmp_path / name / str(k)))
    counts = report.counts()
    assert counts["clean"] == 3 * len(broken), report.table() + "\n" + report.faults_text()
    assert not (tmp_path / "comp.parquet").exists()
