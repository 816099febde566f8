"""`deltatwin emulate` in a real subprocess: the scenario's twin behind pseudo-terminals;
`deltatwin campaign --instruments serial` through it (another real subprocess) equals
`deltatwin campaign --instruments sim`, to the instruments' resolution."""
import json
import os
import signal
import subprocess
import sys

import numpy as np

from deltatwin.cli import main
from deltatwin.hw.ports import load_ports
from deltatwin.twin.dataset import read_dataset

SCALE = 0.002        # paper-thermal: 57 points in two sessions (x/y, then z)
# half the last digit each instrument writes (docs/hardware.md): nm to 0.001, arcsec to 0.01,
# degC to 8 significant digits, encoders (rad) to 13
TOLERANCE = {"_nm": 0.5e-3, "_arcsec": 0.5e-2, "_C": 0.5e-6, "_rad": 0.5e-13}


def _ignore_sigint():
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def test_campaign_through_emulate_matches_the_simulated_instruments(tmp_path):
    """The emulator starts with SIGINT ignored, as a shell's background job (`&`) does, and
    must still stop on SIGINT (it handles the signal itself)."""
    ports_file = tmp_path / "ports.toml"
    proc = subprocess.Popen(
        [sys.executable, "-m", "deltatwin.cli", "emulate", "paper-thermal", "--scale",
         str(SCALE), "--ports-out", str(ports_file), "--dir", str(tmp_path / "dev"), "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_ignore_sigint)
    try:
        first = proc.stdout.readline()
        assert first, proc.stderr.read()
        devices = json.loads(first)["devices"]
        assert set(devices) == {"clock", "robot", "interferometers", "autocollimator1",
                                "autocollimator2", "thermometers", "coils"}
        for d in devices.values():
            assert os.path.realpath(d["url"]) == d["device"]
            assert d["device"].startswith("/dev/pts/")
        ports = load_ports(ports_file)
        assert ports.interferometer_axes == ("x", "y", "z")
        assert len(ports.thermometer_channels) == 11

        campaign = subprocess.run(
            [sys.executable, "-m", "deltatwin.cli", "campaign", "paper-thermal", "--scale",
             str(SCALE), "--instruments", "serial", "--ports", str(ports_file), "-o",
             str(tmp_path / "serial.parquet"), "--quiet", "--json"],
            capture_output=True, text=True, timeout=300)
        assert campaign.returncode == 0, campaign.stderr
        assert json.loads(campaign.stdout)["points"] == 57
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert not any(os.path.lexists(d["url"]) for d in devices.values())   # symlinks gone

    assert main(["campaign", "paper-thermal", "--scale", str(SCALE), "--instruments", "sim",
                 "-o", str(tmp_path / "sim.parquet"), "--quiet"]) == 0
    serial, meta = read_dataset(tmp_path / "serial.parquet")
    direct, meta_sim = read_dataset(tmp_path / "sim.parquet")
    assert meta["instruments"]["kind"] == "serial" and meta["source"] == "lab"
    assert meta["instruments"]["clock"] == "clock port"
    assert meta["instruments"]["ports"]["robot"] == devices["robot"]["url"]
    assert meta_sim["instruments"]["kind"] == "sim" and meta_sim["source"] == "twin"
    assert {k: v for k, v in meta.items() if k not in ("instruments", "source", "campaign")} == \
        {k: v for k, v in meta_sim.items() if k not in ("instruments", "source", "campaign")}
    assert list(serial.columns) == list(direct.columns) and len(serial) == len(direct) == 57
    for c in direct.columns:
        tol = next((t for suffix, t in TOLERANCE.items() if c.endswith(suffix)), None)
        if tol is None:                    # time, ids, currents, flags: exact
            assert serial[c].equals(direct[c]), c
        else:
            np.testing.assert_allclose(serial[c], direct[c], atol=tol, rtol=0, err_msg=c)
    assert serial["z_nm"].isna().sum() > 0 and serial["x_nm"].isna().sum() > 0


def test_emulate_reports_a_bad_scenario(tmp_path):
    r = subprocess.run([sys.executable, "-m", "deltatwin.cli", "emulate", "no-such-scenario"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "deltatwin emulate: error: no-such-scenario: no such scenario file" in r.stderr
