"""Progress on stderr: off a terminal plain lines (no carriage-return runs), at most one per
task every PLAIN_INTERVAL_S and never the same line twice; on a terminal one updating line."""
import io
import logging

import pytest

from deltatwin.cli import main
from deltatwin.progress import PLAIN_INTERVAL_S, ProgressHandler, progress_bar


class Terminal(io.StringIO):
    def isatty(self):
        return True


def _record(msg, task=None):
    r = logging.LogRecord("deltatwin", logging.INFO, __file__, 1, msg, None, None)
    if task:
        r.progress = task
    return r


def test_progress_records_off_a_terminal_are_plain_spaced_lines_never_repeated():
    now = [0.0]
    out = io.StringIO()
    h = ProgressHandler(out, clock=lambda: now[0])
    for t, msg in [(0, "rms 10"), (1, "rms 9"), (2, "rms 9"), (PLAIN_INTERVAL_S + 1, "rms 9"),
                   (PLAIN_INTERVAL_S + 2, "rms 8"), (3 * PLAIN_INTERVAL_S, "rms 7")]:
        now[0] = t
        h.emit(_record(msg, "fit"))
    h.emit(_record("done"))
    assert out.getvalue() == "rms 10\nrms 9\nrms 7\ndone\n"


def test_tqdm_disable_silences_the_status_lines_not_the_results(monkeypatch):
    """TQDM_DISABLE (tqdm's switch) silences our status lines too, so output that must not
    depend on the machine's speed (the generated walkthrough) has none; other records stay."""
    monkeypatch.setenv("TQDM_DISABLE", "1")
    out = io.StringIO()
    h = ProgressHandler(out, clock=lambda: 0.0)
    h.emit(_record("rms 10", "fit"))
    h.emit(_record("done"))
    assert out.getvalue() == "done\n"
    monkeypatch.setenv("TQDM_DISABLE", "0")
    h.emit(_record("rms 9", "fit"))
    assert out.getvalue() == "done\nrms 9\n"


def test_progress_records_on_a_terminal_update_one_line():
    out = Terminal()
    h = ProgressHandler(out)
    for msg in ("rms 10", "rms 9", "rms 9"):
        h.emit(_record(msg, "fit"))
    h.emit(_record("done"))
    text = out.getvalue()
    assert text.count("\n") == 2 and text.endswith("\rrms 9\x1b[K\ndone\n")


def test_a_bar_off_a_terminal_writes_plain_lines():
    out = io.StringIO()
    with progress_bar(total=3, desc="stage", file=out) as bar:
        for name in ("a", "b", "c"):
            bar.set_postfix_str(name)
            bar.update()
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text and text.endswith("\n")
    lines = text.splitlines()
    assert len(lines) == len(set(lines)) and "3/3" in lines[-1]


@pytest.fixture(scope="module")
def force_data(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "force.parquet"
    assert main(["simulate", "paper-force", "--scale", "0.1", "--no-floor", "-q",
                 "-o", str(path)]) == 0
    return path


def test_simulate_and_fit_into_a_log_have_no_carriage_returns_nor_repeats(force_data,
                                                                           tmp_path, capfd):
    """stderr is a file here (not a terminal); a fit that runs its 20 evaluations within a few
    seconds shows its status once, not once per evaluation."""
    capfd.readouterr()
    assert main(["simulate", "paper-force", "--scale", "0.05", "--no-floor",
                 "-o", str(tmp_path / "d.parquet")]) == 0
    assert main(["fit", str(force_data), "--effects", "geometric_errors,magnetic_force"]) == 0
    err = capfd.readouterr().err
    assert "\r" not in err, err
    status = [x for x in err.splitlines() if "calibration rms" in x and x.startswith("fit ")]
    assert 1 <= len(status) <= 2 and len(set(status)) == len(status), err
