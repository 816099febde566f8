"""The campaign journal: append + fsync, resume after kill -9, truncated tail, header check."""
import json
import math
import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from deltatwin.twin.journal import Journal, JournalError, read_journal

HEADER = {"scenario": "thermal_paper", "seed": 3, "hash": "ab12"}


def expected_point(k: int) -> dict:
    """The point a writer records as index k (deterministic, with awkward values)."""
    return {"t_s": k * 10.5 + 1 / 3, "pos_id": k // 2, "split": "cal" if k % 3 else "val",
            "x_nm": math.nan if k % 5 == 0 else k * 1.2345678901234567,
            "ok": bool(k % 2), "q_rad": [k * 1e-3, -k * 1e-3, 0.1]}


WRITER = textwrap.dedent("""
    import sys, time
    sys.path[:0] = [{tests!r}, {root!r}]
    from deltatwin.twin.journal import Journal
    from test_journal import expected_point, HEADER
    journal = Journal.open(sys.argv[1], HEADER)
    n = int(sys.argv[2])
    for k in range(n):
        if k in journal:
            continue
        journal.append(k, expected_point(k))
        print(k, flush=True)          # acknowledged only after append returned (fsync'ed)
        time.sleep(0.002)
    journal.close()
    print("done", flush=True)
""")


def run_writer(path, n, tmp_path):
    script = tmp_path / "writer.py"
    tests = os.path.dirname(os.path.abspath(__file__))
    script.write_text(WRITER.format(tests=tests, root=os.path.dirname(os.path.dirname(tests))))
    return subprocess.Popen([sys.executable, str(script), str(path), str(n)],
                            stdout=subprocess.PIPE, text=True)


def check_points(points: dict, indices) -> None:
    assert list(points) == list(indices)
    for k, p in points.items():
        exp = expected_point(k)
        assert p.keys() == exp.keys()
        for c in exp:
            if isinstance(exp[c], float) and math.isnan(exp[c]):
                assert math.isnan(p[c])
            else:
                assert p[c] == exp[c], (k, c)      # exact float round trip


def test_kill_9_mid_campaign_loses_and_duplicates_nothing(tmp_path):
    path = tmp_path / "run.journal"
    proc = run_writer(path, 10_000, tmp_path)
    acked = []
    for line in proc.stdout:
        acked.append(int(line))
        if len(acked) == 40:
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    header, points = read_journal(path)
    assert header == HEADER
    done = sorted(points)
    assert done == list(range(len(done)))          # a prefix, no hole, no duplicate
    assert set(acked) <= set(done)                 # every acknowledged point is on disk
    assert len(done) < 10_000
    check_points(points, range(len(done)))

    # resume in a new process: completes the rest without repeating anything
    n = len(done) + 25
    proc = run_writer(path, n, tmp_path)
    out = proc.communicate(timeout=60)[0].split()
    assert proc.returncode == 0 and out[-1] == "done"
    assert [int(k) for k in out[:-1]] == list(range(len(done), n))
    with Journal.open(path, HEADER) as journal:
        check_points(journal.points(), range(n))
        assert journal.done() == set(range(n))


def test_truncated_last_line_is_tolerated_and_cut_off(tmp_path, caplog):
    path = tmp_path / "run.journal"
    with Journal.open(path, HEADER) as j:
        for k in range(5):
            j.append(k, expected_point(k))
    whole = path.read_bytes()
    # what a crash in the middle of writing point 5 leaves: part of its line, no newline
    line5 = json.dumps({"index": 5, "point": expected_point(5)}).encode()
    with open(path, "ab") as f:
        f.write(line5[:len(line5) // 2])
    header, points = read_journal(path)            # reading does not change the file
    check_points(points, range(5))
    assert path.read_bytes() != whole
    with Journal.open(path, HEADER) as j:
        assert path.read_bytes() == whole          # the incomplete line is cut off
        assert "incomplete last line" in caplog.text
        assert 5 not in j and j.done() == set(range(5))
        j.append(5, expected_point(5))
        check_points(j.points(), range(6))


def test_mismatched_header_is_refused(tmp_path):
    path = tmp_path / "run.journal"
    Journal.open(path, HEADER).close()
    with pytest.raises(JournalError, match=r"seed: journal 3, now 4.*refusing to resume"):
        Journal.open(path, {**HEADER, "seed": 4})
    with pytest.raises(JournalError, match=r"extra: journal None, now 1"):
        Journal.open(path, {**HEADER, "extra": 1})


def test_damage_in_the_middle_and_duplicates_are_errors(tmp_path):
    path = tmp_path / "run.journal"
    with Journal.open(path, HEADER) as j:
        j.append(0, expected_point(0))
        with pytest.raises(JournalError, match="point 0 is already recorded"):
            j.append(0, expected_point(0))
        j.append(1, expected_point(1))
    lines = path.read_bytes().split(b"\n")
    damaged = b"\n".join([lines[0], lines[1][:10], lines[2], b""])
    path.write_bytes(damaged)
    with pytest.raises(JournalError, match="line 2 is damaged"):
        read_journal(path)
    path.write_bytes(b"\n".join([lines[0], lines[1], lines[1], b""]))
    with pytest.raises(JournalError, match="line 3: point 0 recorded twice"):
        Journal.open(path, HEADER)


def test_numpy_values_and_exclusive_lock(tmp_path):
    path = tmp_path / "run.journal"
    with Journal.open(path, {**HEADER, "seed": np.int64(3)}) as j:
        j.append(np.int64(0), {"x_nm": np.float64(0.1) + np.float64(0.2),
                               "q_rad": np.array([1.0, 2.0]), "n": np.int32(7)})
        with pytest.raises(JournalError, match="in use by another process"):
            Journal.open(path, HEADER)
        assert j.points() == {0: {"x_nm": 0.30000000000000004, "q_rad": [1.0, 2.0], "n": 7}}
    with pytest.raises(JournalError, match="not a deltatwin journal header"):
        (tmp_path / "bad").write_text('{"a": 1}\n')
        read_journal(tmp_path / "bad")
