"""`deltatwin campaign`: kill -9 of a real subprocess then --resume; instrument faults injected
by the emulators in the middle of a campaign (retried, logged, completed); persistent faults
stop the campaign with the journal intact, and --resume completes it; refusals."""
import logging
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from deltatwin.cli import main
from deltatwin.hw.emulators.lab import EmulatedLab
from deltatwin.hw.ports import write_ports
from deltatwin.hw.retry import RetryPolicy
from deltatwin.twin.dataset import read_dataset
from deltatwin.twin.instruments.simulated import SimulatedLab
from deltatwin.twin.journal import read_journal
from deltatwin.twin.scenario import SCENARIO_DIR, Scenario

RESOLUTION_NM = 1.24          # the simulated interferometers' resolution (InstrumentSettings)
FAULT_SCALE = 0.0003          # paper-thermal: 8 points, sessions xy (4) then z (4)
FAULT_LINE_TIMEOUT_S = 1.0    # generous: the backing twin answers within ms, even under load
# waits 0.05, 0.1, 0.2, 0.4 s: rides out a port away for 0.3 s
CAMPAIGN_RETRY = RetryPolicy(attempts=5, first_delay_s=0.05, factor=2.0, max_delay_s=0.5)
# half the requests each instrument answers in the fault campaign (counted on a clean run:
# robot 21, interferometers 12, thermometers 18, clock 56, autocollimator1 43): a fault placed
# "after" these falls in the middle of the campaign, past every set-up exchange
MIDWAY = {"robot": 10, "interferometers": 6, "thermometers": 9, "clock": 28,
          "autocollimator1": 21}


def campaign_cmd(out, scale, *extra, scenario="paper-thermal"):
    return ["campaign", str(scenario), "--scale", str(scale), "-o", str(out), "--quiet",
            *extra]


def test_kill_9_then_resume_every_point_once_and_as_uninterrupted(tmp_path):
    """Kill -9 the campaign (simulated instruments) after >= 10 journaled points, in its first
    session; --resume in a new process. Compared with an uninterrupted run:
    * the journal holds every point exactly once; the dataset has every point once, in order;
    * points journaled before the kill: every column identical;
    * the points after: plan columns identical; t_s later by one constant (the re-homing and
      re-zeroing of the resume); in the interrupted session every interferometer reading differs
      by one constant per axis (the home position's drift between the session's zero and the
      resume's zero), to one resolution step; in the next session (its own zero in both runs)
      by at most one resolution step (plus up to 0.2 nm in both: the cosine correction uses
      the autocollimator readings, whose noise draws differ); autocollimators and thermometers
      within their noise (other draws: one more autocollimator reading, scans at other times).
    The resumed points are taken later, so the loop's drift during that delay adds to the
    constant: the test runs paper-thermal on a symmetric portal frame (no frame arm), whose
    drift over the delay stays below the resolution (with the 0.6 m arm the X differences spread
    over 2.5 nm, measured)."""
    scale = 0.004                                   # 114 points: 55 in session xy, 59 in z
    text = (SCENARIO_DIR / "paper-thermal.toml").read_text()
    assert "frame_arm_m = [-0.6, 0.0]" in text
    scenario = tmp_path / "paper-thermal-portal.toml"
    scenario.write_text(text.replace("frame_arm_m = [-0.6, 0.0]", "frame_arm_m = [0.0, 0.0]"))
    out = tmp_path / "run.parquet"
    journal = tmp_path / "run.parquet.journal"
    proc = subprocess.Popen([sys.executable, "-m", "deltatwin.cli",
                             *campaign_cmd(out, scale, scenario=scenario),
                             "--instruments", "sim"], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (journal.exists() and journal.read_bytes().count(b"\n") >= 11):   # header + 10
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline, "no journaled point within 120 s"
        time.sleep(0.002)                           # polling the file, not a synchronisation
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists()
    _, before = read_journal(journal)
    m = len(before)
    assert 10 <= m < 55 and sorted(before) == list(range(m))

    assert main([*campaign_cmd(out, scale, "--resume", scenario=scenario), "--instruments", "sim"]) == 0
    _, points = read_journal(journal)               # kept; a duplicate would be an error here
    df, meta = read_dataset(out)
    full, _ = Scenario.load(scenario).run(scale, progress=False)
    n = len(full)
    assert n == 114 and sorted(points) == list(range(n)) and len(df) == n
    assert meta["campaign"]["taken_before_resume"] == m
    zeros = meta["campaign"]["zeros"]
    assert [(z["session"], z["first_point"], z["after_resume"]) for z in zeros] == [
        ("xy", 0, False), ("xy", m, True), ("z", 55, False)]
    assert zeros[1]["t_s"] > df["t_s"][m - 1]       # the clock ran on after the last point

    assert df.iloc[:m].equals(full.iloc[:m])
    plan_cols = ["pos_id", "split", "session", "q1_rad", "q2_rad", "q3_rad", "coil1_A",
                 "coil2_A", "coil3_A", "F_N", "cosine_corrected"]
    assert df[plan_cols].equals(full[plan_cols])
    shift = (df["t_s"] - full["t_s"]).to_numpy()[m:]
    assert shift[0] > 5.0 and np.ptp(shift) < 1e-6
    after = np.arange(n) >= m
    xy = (df["session"] == "xy").to_numpy()
    for a in ("x", "y"):
        d = (df[f"{a}_nm"] - full[f"{a}_nm"]).to_numpy()[after & xy]
        assert np.ptp(d) <= RESOLUTION_NM + 0.2, (a, d)
    dz = (df["z_nm"] - full["z_nm"]).to_numpy()[~xy]
    assert np.max(np.abs(dz)) <= RESOLUTION_NM + 0.2
    ac = [c for c in df.columns if c.endswith("_arcsec")]
    assert np.nanmax(np.abs(df[ac].to_numpy() - full[ac].to_numpy())) < 0.25    # ~6 sigma
    T = [c for c in df.columns if c.startswith("T_")]
    assert np.max(np.abs(df[T].to_numpy() - full[T].to_numpy())) < 0.025      # ~6 sigma


@pytest.fixture(scope="module")
def reference():
    """The fault campaign's dataset with the simulated instruments directly."""
    df, _ = Scenario.load("paper-thermal").run(FAULT_SCALE, progress=False)
    return df


@pytest.fixture
def lab(tmp_path):
    """The scenario's twin behind emulators on ptys (as `deltatwin emulate` serves it) and its
    ports file; fast retries, generous reply timeouts."""
    sc = Scenario.load("paper-thermal")
    twin, _ = sc.build(FAULT_SCALE)
    with EmulatedLab(SimulatedLab(twin, sc.settings).instrument_set(), tmp_path / "dev",
                     timeout_s=FAULT_LINE_TIMEOUT_S, retry=CAMPAIGN_RETRY) as lab:
        write_ports(tmp_path / "ports.toml", lab.ports())
        yield lab, tmp_path / "ports.toml"


def serial_campaign(tmp_path, ports, *extra):
    return main([*campaign_cmd(tmp_path / "run.parquet", FAULT_SCALE, *extra),
                 "--instruments", "serial", "--ports", str(ports)])


def check_complete(tmp_path, reference):
    """Every point once, in order; faults only ever add time; readings as the simulated
    instruments' within noise (a repeated exchange may consume other noise draws)."""
    df, meta = read_dataset(tmp_path / "run.parquet")
    _, points = read_journal(tmp_path / "run.parquet.journal")
    n = len(reference)
    assert n == 8 and sorted(points) == list(range(n)) and len(df) == n
    assert meta["source"] == "lab" and meta["instruments"]["kind"] == "serial"
    assert (df["pos_id"] == reference["pos_id"]).all()
    assert np.all(df["t_s"].to_numpy() >= reference["t_s"].to_numpy() - 1e-9)
    for c in ("x_nm", "y_nm", "z_nm"):
        assert (df[c].isna() == reference[c].isna()).all(), c
        assert np.nanmax(np.abs(df[c] - reference[c])) < 50.0, c     # noise ~7 nm here
    # temperatures: where the faults cost less than a minute (a lost reply to the clock's
    # SLEEP during the 30-minute session gap makes the retry wait it again: time passes)
    T = [c for c in df.columns if c.startswith("T_")]
    close = (df["t_s"] - reference["t_s"]).to_numpy() < 60.0
    assert close.sum() >= 4
    assert np.max(np.abs(df[T].to_numpy() - reference[T].to_numpy())[close]) < 0.05
    return df, meta


FAULTS = [("robot", "no_reply"), ("interferometers", "garbled"), ("thermometers", "truncated"),
          ("clock", "dropped_bytes"), ("autocollimator1", "error_code"), ("robot", "vanish"),
          ("thermometers", "vanish")]


@pytest.mark.parametrize("instrument,fault", FAULTS)
def test_fault_mid_campaign_is_retried_logged_and_the_campaign_completes(
        tmp_path, lab, reference, caplog, instrument, fault):
    emulated, ports = lab
    emu = emulated.emulators[instrument]
    emu.inject(fault, after=MIDWAY[instrument], down_s=0.3)
    with caplog.at_level(logging.WARNING):
        assert serial_campaign(tmp_path, ports) == 0
    assert emu.faults_applied[fault] == 1
    assert f"{instrument}: " in caplog.text and "attempt 1/5 failed" in caplog.text
    if fault == "vanish":
        assert "PortLost" in caplog.text
    check_complete(tmp_path, reference)


def test_turbulent_window_is_taken_again(tmp_path, lab, reference, caplog):
    """A window whose sample std fails the acceptance rule is rejected and read again."""
    emulated, ports = lab
    emulated.emulators["interferometers"].inject("turbulence", count=2, after=3)
    with caplog.at_level(logging.INFO, logger="deltatwin.twin.campaign"):
        assert serial_campaign(tmp_path, ports) == 0
    assert emulated.emulators["interferometers"].faults_applied["turbulence"] == 2
    assert caplog.text.count("window rejected") == 2 and "taking it again" in caplog.text
    df, _ = check_complete(tmp_path, reference)
    assert df[["x_std_nm", "y_std_nm"]].max().max() < 10.0
    # two windows more: every point from the disturbed one on is later by 2 windows
    assert df["t_s"].iloc[-1] - reference["t_s"].iloc[-1] == pytest.approx(2 * 0.2, abs=1e-9)


@pytest.mark.parametrize("instrument,fault,message", [
    ("interferometers", "error_code",
     r"interferometers: read failed 5 time\(s\) .* last error: injected fault \[5\]"),
    ("interferometers", "turbulence",
     r"interferometers: point {k}: sample std above 10 nm in 21 windows in a row"),
    ("robot", "vanish", r"robot: \w+ failed 5 time\(s\) .* last error: cannot open .*/robot"),
])
def test_persistent_fault_stops_with_journal_intact_then_resume_completes(
        tmp_path, lab, reference, capsys, instrument, fault, message):
    emulated, ports = lab
    emu = emulated.emulators[instrument]
    emu.inject(fault, count=None, after=MIDWAY[instrument], down_s=600.0)
    assert serial_campaign(tmp_path, ports) == 3
    err = capsys.readouterr().err
    _, points = read_journal(tmp_path / "run.parquet.journal")
    k = len(points)
    assert 0 < k < 8 and sorted(points) == list(range(k))
    assert re.search(rf"stopped by an instrument fault at point {k} of 8: "
                     + message.replace("{k}", str(k)), err), err
    assert f"{k} point(s) are safe in the journal" in err and "--resume" in err
    assert not (tmp_path / "run.parquet").exists()

    emu.clear_faults()                              # the cause fixed (the port back)
    assert serial_campaign(tmp_path, ports, "--resume") == 0
    _, meta = check_complete(tmp_path, reference)
    assert meta["campaign"]["taken_before_resume"] == k
    assert any(z["after_resume"] and z["first_point"] == k for z in meta["campaign"]["zeros"])


def test_refusals(tmp_path, capsys):
    out = tmp_path / "run.parquet"
    assert main([*campaign_cmd(out, FAULT_SCALE), "--instruments", "sim"]) == 0
    assert main([*campaign_cmd(out, FAULT_SCALE), "--instruments", "sim"]) == 2
    assert "run.parquet.journal exists: continue that run with --resume" in \
        capsys.readouterr().err
    assert main([*campaign_cmd(out, FAULT_SCALE, "--resume", "--seed", "2"),
                 "--instruments", "sim"]) == 2
    err = capsys.readouterr().err
    assert "written for another campaign (seed: journal 1, now 2)" in err
    assert "refusing to resume" in err
    assert main([*campaign_cmd(out, 0.0005, "--resume"), "--instruments", "sim"]) == 2
    assert "points: journal 8, now 14" in capsys.readouterr().err
    assert main([*campaign_cmd(tmp_path / "other.parquet", FAULT_SCALE, "--resume"),
                 "--instruments", "sim"]) == 2
    assert "no journal" in capsys.readouterr().err
    assert main([*campaign_cmd(out, FAULT_SCALE), "--instruments", "serial"]) == 2
    assert "needs --ports FILE" in capsys.readouterr().err
    # a completed campaign resumed: nothing taken again, the same dataset
    first, _ = read_dataset(out)
    assert main([*campaign_cmd(out, FAULT_SCALE, "--resume"), "--instruments", "sim"]) == 0
    again, meta = read_dataset(out)
    assert again.equals(first) and meta["campaign"]["taken_before_resume"] == 8


def test_wall_clock_continues_after_a_resume(tmp_path):
    """A laboratory without a clock port: the resumed campaign's time is the last journaled
    point's time plus the wall time since it was journaled."""
    import os

    from deltatwin.commands.campaign import resumed_wall_clock_s
    from deltatwin.hw.clock import WallClock
    from deltatwin.twin.journal import Journal

    assert resumed_wall_clock_s(tmp_path / "j") == 0.0              # no journal yet
    with Journal.open(tmp_path / "j", {"scenario": "s"}) as journal:
        assert resumed_wall_clock_s(journal.path) == 0.0
        journal.append(0, {"t_s": 100.0})
        stamp = time.time() - 50.0
        os.utime(journal.path, (stamp, stamp))
        start = resumed_wall_clock_s(journal.path)
    assert 150.0 <= start < 155.0
    clock = WallClock(start)
    assert start <= clock.now() < start + 5.0


def test_sim_resume_replays_the_journal_and_refuses_a_world_that_differs(tmp_path, capsys):
    """--instruments sim rebuilds the world and replays the journaled points; a journal whose
    points the rebuilt world does not reproduce is refused (nothing written)."""
    out = tmp_path / "run.parquet"
    journal = tmp_path / "run.parquet.journal"
    assert main([*campaign_cmd(out, FAULT_SCALE), "--instruments", "sim"]) == 0
    complete, _ = read_dataset(out)
    lines = journal.read_bytes().split(b"\n")
    out.unlink()
    journal.write_bytes(b"\n".join(lines[:4]) + b"\n")             # header + points 0, 1, 2
    assert main([*campaign_cmd(out, FAULT_SCALE, "--resume"), "--instruments", "sim"]) == 0
    resumed, meta = read_dataset(out)
    assert resumed.iloc[:3].equals(complete.iloc[:3]) and len(resumed) == 8
    assert [z["first_point"] for z in meta["campaign"]["zeros"] if z["after_resume"]] == [3]

    out.unlink()
    journal.write_bytes(b"\n".join(lines[:2] + [lines[2].replace(b'"t_s":', b'"t_s":1')])
                        + b"\n")
    assert main([*campaign_cmd(out, FAULT_SCALE, "--resume"), "--instruments", "sim"]) == 2
    assert "point 1 taken again in the rebuilt simulated world differs from the journal" in \
        capsys.readouterr().err
    assert not out.exists()


def world_lab(tmp_path, seed):
    """paper-thermal of ``seed`` behind emulators that say so on the clock port (WORLD?)."""
    sc = Scenario.load("paper-thermal", seed=seed)
    twin, _ = sc.build(FAULT_SCALE)
    return EmulatedLab(SimulatedLab(twin, sc.settings).instrument_set(), tmp_path / "dev",
                       timeout_s=FAULT_LINE_TIMEOUT_S, retry=CAMPAIGN_RETRY,
                       world=sc.identity(FAULT_SCALE))


def test_emulator_of_another_seed_is_refused(tmp_path, capsys):
    """`emulate --seed 7` and a campaign of the default seed (1): refused before anything is
    measured, naming the seed; no journal is left behind; with --seed 7 the same command runs."""
    with world_lab(tmp_path, seed=7) as lab:
        write_ports(tmp_path / "ports.toml", lab.ports())
        assert serial_campaign(tmp_path, tmp_path / "ports.toml") == 2
        err = capsys.readouterr().err
        assert "simulates another campaign (seed: emulator 7, campaign 1)" in err, err
        assert not (tmp_path / "run.parquet.journal").exists()
        assert serial_campaign(tmp_path, tmp_path / "ports.toml", "--seed", "7") == 0
    df, meta = read_dataset(tmp_path / "run.parquet")
    assert meta["seed"] == 7 and len(df) == 8


def test_connect_failure_leaves_no_journal_and_a_plain_rerun_works(lab, tmp_path, capsys):
    emulated, ports = lab
    good = ports.read_text()
    robot_url = emulated.emulators["robot"].url
    ports.write_text(good.replace(robot_url, str(tmp_path / "no-such-device")))
    assert serial_campaign(tmp_path, ports) == 3
    err = capsys.readouterr().err
    assert "cannot start" in err and "no-such-device" in err and "no journal written" in err
    assert not (tmp_path / "run.parquet.journal").exists()
    ports.write_text(good)
    assert serial_campaign(tmp_path, ports) == 0                # no --resume needed


def test_ctrl_c_says_how_many_points_are_safe_and_to_resume(tmp_path, capsys, monkeypatch):
    """Ctrl-C (KeyboardInterrupt) after 3 journaled points: exit 130, the message counts the
    safe points and names --resume; the resume completes every point once."""
    from deltatwin.twin.journal import Journal
    append = Journal.append

    def append_then_interrupt(self, index, point):
        append(self, index, point)
        if index == 2:
            raise KeyboardInterrupt
    monkeypatch.setattr(Journal, "append", append_then_interrupt)
    out = tmp_path / "run.parquet"
    assert main([*campaign_cmd(out, FAULT_SCALE), "--instruments", "sim"]) == 130
    err = capsys.readouterr().err
    assert "interrupted" in err and "3 point(s) are safe in the journal" in err, err
    assert "(5 to go)" in err
    assert "run the same command with --resume" in err
    monkeypatch.setattr(Journal, "append", append)
    assert main([*campaign_cmd(out, FAULT_SCALE), "--instruments", "sim", "--resume"]) == 0
    _, points = read_journal(tmp_path / "run.parquet.journal")
    assert sorted(points) == list(range(8))
