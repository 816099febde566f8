"""The same compensated campaign through the serial drivers and emulators equals the simulated
one to the instruments' resolution: the same decisions (motor coordinates), the same
readings."""
import json

import numpy as np
import pandas as pd

from deltatwin.calibration.compensation import NominalCompensator
from deltatwin.cli import main
from deltatwin.commands.compensate import compensation_plan, compensation_world
from deltatwin.hw.emulators.lab import EmulatedLab
from deltatwin.hw.ports import write_ports
from deltatwin.twin.scenario import Scenario
from tests.deltatwin.test_compensate_cli import TARGETS, lab  # noqa: F401  (the fixture)

RESOLUTION_NM = 1.24


def _compensate(d, capsys, out, *extra):
    code = main(["compensate", str(d / "lab.toml"), "--model", str(d / "true.toml"),
                 "--data", str(d / "cal.parquet"), "--targets", str(TARGETS), "--seed", "3",
                 "-o", str(out), "--json", "--quiet", *extra])
    text = capsys.readouterr().out
    assert code == 0, text
    return json.loads(text.strip().splitlines()[-1])


def test_serial_compensated_campaign_equals_the_simulated_one(lab, capsys, tmp_path):  # noqa: F811
    sim = _compensate(lab, capsys, tmp_path / "sim.parquet")
    sc = Scenario.load(lab / "lab.toml")
    plan, *_ = compensation_plan(sc, np.random.default_rng(3), TARGETS,
                                 NominalCompensator(sc.params), ("x", "y", "z"))
    _, world = compensation_world(sc, None, 2.0, plan, 3)
    with EmulatedLab(world.instrument_set(), tmp_path / "dev") as emulated:
        write_ports(tmp_path / "ports.toml", emulated.ports())
        serial = _compensate(lab, capsys, tmp_path / "serial.parquet", "--instruments",
                             "serial", "--ports", str(tmp_path / "ports.toml"))
    a = pd.read_parquet(tmp_path / "sim.parquet")
    b = pd.read_parquet(tmp_path / "serial.parquet")
    assert len(a) == len(b) == 2 * TARGETS
    assert (a["status"] == b["status"]).all() and (a["command"] == b["command"]).all()
    # the decisions: the temperatures and times travel as text (8 digits: 5e-8 degC, 3e-8 s
    # measured), and a scan exactly 600 s old sits on the smoothing window's edge, in or out by
    # those 3e-8 s: q differ by up to 1.7e-9 rad (measured), ~0.1 nm at the end-effector
    q = ["q1_rad", "q2_rad", "q3_rad"]
    assert np.abs(b[q].to_numpy() - a[q].to_numpy()).max() < 1e-8
    for c in ("x_nm", "y_nm", "z_nm"):
        assert np.abs(a[c] - b[c]).max() <= RESOLUTION_NM * (1 + 1e-6), c   # one step at most
    T = [c for c in a.columns if c.startswith("T_")]
    assert np.abs(a[T].to_numpy() - b[T].to_numpy()).max() < 1e-6
    for ax in "xyz":
        assert abs(sim["axes"][ax]["achieved_err90_nm"]
                   - serial["axes"][ax]["achieved_err90_nm"]) <= RESOLUTION_NM
