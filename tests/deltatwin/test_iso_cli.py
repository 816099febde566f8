"""``deltatwin iso`` end to end on scaled-down tests: the report and its figures, the same figures
from the test's campaign run point by point by ``deltatwin campaign`` (the journaled path) and
through the serial drivers and emulators, and bad input refused in one line."""
import json

import numpy as np
import pandas as pd
import pytest

from deltatwin.cli import main
from deltatwin.hw.emulators.lab import EmulatedLab
from deltatwin.hw.ports import write_ports
from deltatwin.twin.instruments.simulated import SimulatedLab
from deltatwin.twin.scenario import Scenario

RESOLUTION_NM = 1.24
CAL_SCALE = 0.05          # the calibration campaign of the compensated test


def _iso(capsys, *args):
    code = main(["iso", *args, "--json", "--quiet"])
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def iso9283(tmp_path_factory):
    d = tmp_path_factory.mktemp("iso9283")
    code = main(["iso", "paper-thermal", "--test", "9283", "--cycles", "4", "-o", str(d / "r"),
                 "--tolerance", "AP=500", "--quiet", "--json"])
    assert code == 0
    return d


def test_iso9283_report_and_figures(iso9283):
    r = iso9283 / "r"
    doc = json.loads((r / "results.json").read_text())
    poses = doc["arms"]["uncompensated"]["poses"]
    assert list(poses) == ["P1", "P2", "P3", "P4", "P5"] and poses["P1"]["n"] == 4
    assert doc["parameters"]["order"] == ["P5", "P4", "P3", "P2", "P1"]
    text = (r / "report.md").read_text()
    assert "![iso9283.png](iso9283.png)" in text and "## Uncertainty budget" in text
    assert (r / "iso9283.png").stat().st_size > 10_000
    ap = [row for row in doc["figures"] if row["figure"].startswith("AP ")]
    assert len(ap) == 5 and all(row["U_nm"] > 0 and "decision" in row for row in ap)
    for row in ap:     # the guard band: conforms only below T - U
        v, U = row["value_nm"], row["U_nm"]
        assert row["decision"] == ("conforms" if v <= 500 - U else "does not conform"
                                   if v > 500 + U else "inconclusive")


def test_iso_figures_equal_the_campaign_commands_run(iso9283, capsys):
    """The test's scenario run point by point by `deltatwin campaign` (journaled) and evaluated
    with --data gives the figures of the fast path exactly."""
    data = iso9283 / "campaign.parquet"
    assert main(["campaign", str(iso9283 / "r" / "scenario.toml"), "--instruments", "sim",
                 "-o", str(data), "--quiet"]) == 0
    capsys.readouterr()
    doc = _iso(capsys, "paper-thermal", "--test", "9283", "--cycles", "4", "--data", str(data),
               "-o", str(iso9283 / "d"))
    fast = json.loads((iso9283 / "r" / "results.json").read_text())["arms"]["uncompensated"]
    assert doc["arms"]["measured"]["poses"] == fast["poses"]
    # the dataset of another test's campaign is refused, in one line
    for other, words in ((["--cycles", "5"], "not this test's"), (["--cycles", "4", "--scale",
                                                                  "0.5"], "at scale 1")):
        code = main(["iso", "paper-thermal", "--test", "9283", *other, "--data", str(data),
                     "-o", str(iso9283 / "e")])
        err = capsys.readouterr().err
        assert code == 2 and words in err and len(err.strip().splitlines()) == 1, err


def test_iso230_2_serial_path_equals_the_simulated_one(tmp_path, capsys):
    args = ["paper-thermal", "--test", "230-2", "--axes", "x,z", "--targets", "3",
            "--approaches", "2"]
    sim = _iso(capsys, *args, "-o", str(tmp_path / "sim"))
    sc = Scenario.load(tmp_path / "sim" / "scenario.toml")
    twin, _ = sc.build()
    with EmulatedLab(SimulatedLab(twin, sc.settings).instrument_set(), tmp_path / "dev") as lab:
        write_ports(tmp_path / "ports.toml", lab.ports())
        ser = _iso(capsys, *args, "-o", str(tmp_path / "ser"), "--instruments", "serial",
                   "--ports", str(tmp_path / "ports.toml"))
    a = pd.read_parquet(tmp_path / "sim" / "arm0.parquet")
    b = pd.read_parquet(tmp_path / "ser" / "arm0.parquet")
    for c in ("x_nm", "z_nm"):
        m = np.isfinite(a[c])
        assert m.sum() > 0 and (np.isfinite(b[c]) == m).all()
        assert np.abs(a[c][m] - b[c][m]).max() <= RESOLUTION_NM * (1 + 1e-6), c
    for axis in ("x", "z"):
        s = sim["arms"]["uncompensated"][axis]["axis_figures"]
        e = ser["arms"]["serial"][axis]["axis_figures"]
        for k, v in s.items():
            assert abs(v - e[k]) <= 4 * RESOLUTION_NM, (axis, k)   # ranges: 2 readings, 2 s


def test_iso230_3_report(tmp_path, capsys):
    doc = _iso(capsys, "paper-thermal", "--test", "230-3", "--hours", "0.5", "-o",
               str(tmp_path / "r"))
    etve = doc["arms"]["uncompensated"]
    assert etve["duration_h"] == pytest.approx(0.5, abs=0.01)
    assert set(etve["directions"]) == {"x", "y", "z"}
    assert (tmp_path / "r" / "iso230-3.png").exists()


@pytest.mark.parametrize("args, words", [
    (["--test", "9283", "--targets", "5"], "--targets is not an option of --test 9283"),
    (["--test", "9283", "--cycles", "1"], "cycles = 1: must be >= 2"),
    (["--test", "230-2", "--axes", "x,w"], "axes ['x', 'w']"),
    (["--test", "9283", "--tolerance", "AP=much"], "--tolerance 'AP=much'"),
    (["--test", "230-3", "--hours", "-1"], "duration_h"),
    (["--test", "9283", "--scale", "2"], "--scale must be in (0, 1]"),
    (["--test", "9283", "--compensate", "nope.toml"], "--compensate nope.toml"),
    (["--test", "9283", "--instruments", "serial"], "--instruments serial needs --ports"),
    (["--test", "230-3", "--interval", "3"], "--interval 3 s: a reading at rest takes 8 s"),
    (["--test", "9283", "--interval", "60"], "--interval is not an option of --test 9283"),
    (["--test", "9283", "--wait", "-1"], "--wait must be in [0, 3600] s"),
])
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, args, words):
    code = main(["iso", "paper-thermal", *args, "-o", str(tmp_path / "r")])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and words in err, err
    assert not (tmp_path / "r").exists()


def test_iso9283_drift_and_iso230_3_interval(tmp_path, capsys):
    doc = _iso(capsys, "paper-thermal", "--test", "9283", "--cycles", "4", "--drift-cycles",
               "2", "-o", str(tmp_path / "a"))
    p1 = doc["arms"]["uncompensated"]["poses"]["P1"]
    assert p1["dAP_nm"] is not None and any(r["figure"] == "dRP P3" for r in doc["figures"])
    doc = _iso(capsys, "paper-thermal", "--test", "230-3", "--hours", "0.5", "--interval", "60",
               "--wait", "10", "-o", str(tmp_path / "b"))
    t = pd.read_parquet(tmp_path / "b" / "arm0.parquet")["t_s"].to_numpy()
    assert doc["arms"]["uncompensated"]["n"] == 30
    assert np.median(np.diff(t)) == pytest.approx(60.0, abs=0.5)


@pytest.mark.slow
def test_iso9283_through_a_fitted_physics_model(tmp_path, capsys):
    """Commanded through a physics model fitted on a small calibration campaign of the same
    robot, its largest AP falls below a tenth of the uncompensated one; the arms side by side
    in the report."""
    from deltatwin.calibration.physics.fit import PhysicsFit
    from deltatwin.calibration.physics.model import model_effects
    from deltatwin.calibration.physics.model_file import fitted_toml

    sc = Scenario.load("paper-thermal")
    df, meta = sc.simulate(CAL_SCALE)
    effects = [e.name for e in sc.effects if e.name in model_effects()]
    known = {e.name: {p.name: e.values[p.name] for p in e.parameters if p.fit_scale is None}
             for e in sc.effects if e.name in effects}
    fit = PhysicsFit(effects, start=known).fit(df, meta)
    (tmp_path / "phys.toml").write_text(fitted_toml(fit, str(tmp_path / "cal.parquet")))
    out = _iso(capsys, "paper-thermal", "--test", "9283", "--cycles", "2", "--compensate",
               str(tmp_path / "phys.toml"), "--cal-scale", str(CAL_SCALE), "-o",
               str(tmp_path / "r"))
    ap = {arm: r["AP_max_nm"] for arm, r in out["arms"].items()}
    assert list(ap) == ["uncompensated", "physics (phys.toml)"]
    assert ap["physics (phys.toml)"] < ap["uncompensated"] / 10, ap
    assert "physics (phys.toml)" in (tmp_path / "r" / "report.md").read_text()


@pytest.mark.parametrize("test", ["9283", "230-2", "230-3"])
def test_paper_force_robot_reduced(tmp_path, capsys, test):
    doc = _iso(capsys, "paper-force", "--test", test, "--reduced", "-o", str(tmp_path / "r"))
    assert doc["scenario"] == "paper-force" and doc["figures"]
    assert all(np.isfinite(r["value_nm"]) and r["U_nm"] > 0 for r in doc["figures"])
    assert (tmp_path / "r" / "report.md").exists()
