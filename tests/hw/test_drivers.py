"""Every driver against its emulator over real pseudo-terminals (pyserial), backed by the toy
lab: the readings through the serial path equal the toy lab's own, to each instrument's
resolution; instrument-specific behaviour (units, ranges, overflow, set-up errors)."""
import logging
import math

import numpy as np
import pytest

from deltatwin.hw.emulators.lab import EmulatedLab
from deltatwin.hw.lab import open_lab
from deltatwin.hw.protocol import InstrumentRejected, SerialLine
from deltatwin.twin.instruments.interface import InstrumentError
from tests.hw.conftest import ARCSEC, FAST_RETRY, LINE_TIMEOUT_S, toy_lab

POINTS = [np.array([0.01, -0.02, 0.03]), np.array([0.19, 0.19, 0.0]),   # ac2_rz out of range
          np.array([-0.05, 0.1, -0.15])]


def session(inst):
    """A small campaign-like sequence of interface calls; returns everything read."""
    out = []
    inst.robot.move_to(np.zeros(3))
    inst.clock.sleep(5.0)
    inst.interferometers.zero()
    for k, q in enumerate(POINTS):
        inst.coils.set_currents(np.array([0.5 * k, 1.0, -0.25]))
        inst.robot.move_to(q)
        inst.clock.sleep(1.5)
        out.append(dict(t=inst.clock.now(), ifm=inst.interferometers.read(),
                        ac=inst.autocollimators.read(), T=inst.thermometers.scan(),
                        enc=inst.robot.read_encoders(), I=inst.coils.read_currents()))
    return out


def assert_same(serial, direct, ac_tol_rad):
    assert len(serial) == len(direct)
    for s, d in zip(serial, direct):
        assert s["t"] == d["t"]                                   # the clock is exact
        for a in ("x", "y"):
            assert s["ifm"].displacement_m[a] == pytest.approx(d["ifm"].displacement_m[a],
                                                               abs=0.5e-12)
            assert s["ifm"].std_m[a] == pytest.approx(d["ifm"].std_m[a], abs=0.5e-12)
        assert (s["ifm"].n_samples, s["ifm"].window_s) == (d["ifm"].n_samples,
                                                           d["ifm"].window_s)
        assert s["ac"].in_range == d["ac"].in_range
        for c, v in d["ac"].angles_rad.items():
            if math.isnan(v):
                assert math.isnan(s["ac"].angles_rad[c])
            else:
                assert s["ac"].angles_rad[c] == pytest.approx(v, abs=ac_tol_rad)
        assert s["T"].temperatures_C.keys() == d["T"].temperatures_C.keys()
        for n, v in d["T"].temperatures_C.items():
            assert s["T"].temperatures_C[n] == pytest.approx(v, abs=0.5e-7)
        np.testing.assert_allclose(s["enc"], d["enc"], rtol=1e-12)
        np.testing.assert_allclose(s["I"], d["I"], atol=0.5e-6, rtol=0)


def test_every_driver_matches_the_backing_instruments(emulated, drivers):
    backing, lab = emulated
    serial = session(drivers)
    direct = session(toy_lab())              # same seed, same calls, no serial link
    assert any(not r["ac"].in_range["ac2_rz"] for r in direct)
    assert_same(serial, direct, ac_tol_rad=0.005 * ARCSEC)    # 0.01 arcsec display step
    # one backing call per interface call: the emulators add nothing
    assert backing.robot.moves == 4
    assert backing.interferometers.reads == backing.autocollimators.reads == 3
    assert backing.thermometers.scans == 3
    assert drivers.thermometers.sensors == ("air_x", "air_y", "base", "arm1")
    assert drivers.autocollimators.channels == ToyChannels


ToyChannels = ("ac1_ry", "ac1_rz", "ac2_rx", "ac2_rz")


def test_autocollimators_in_microradians_and_refused_linear_units(emulated):
    backing, lab = emulated
    for name, unit in (("autocollimator1", "µrad"), ("autocollimator2", "mrad")):
        lab.emulators[name].unit = unit
    inst = open_lab(lab.ports())
    serial = session(inst)
    inst.close()
    assert_same(serial, session(toy_lab()), ac_tol_rad=0.05e-6)   # 0.1 µrad display step
    # a controller set to a linear unit is refused at connection, without retrying
    lab.emulators["autocollimator2"].unit = "mm"
    inst = open_lab(lab.ports())
    before = lab.emulators["autocollimator2"].requests
    with pytest.raises(InstrumentRejected, match=r"axis 1 is set to unit 'mm'; set an angle "
                                                 r"unit"):
        inst.autocollimators.read()
    assert lab.emulators["autocollimator2"].requests - before == 3        # MR, VE, 1TA: once
    inst.close()


def test_keithley_overflow_names_channel_and_sensor(emulated, drivers, caplog):
    backing, lab = emulated
    lab.emulators["thermometers"].open_channels = {103}
    with pytest.raises(InstrumentError, match=r"scan failed 4 time\(s\).*overflow \(\+9\.9E37\) "
                                              r"on channel\(s\) 103 \(base\): open or unplugged "
                                              r"PT100\? \[overflow\]"):
        drivers.thermometers.scan()
    lab.emulators["thermometers"].open_channels = set()
    assert set(drivers.thermometers.scan().temperatures_C) == {"air_x", "air_y", "base", "arm1"}


def test_keithley_channel_without_sensor_and_channel_off_the_card(emulated):
    backing, lab = emulated
    ports = lab.ports()
    ports.thermometer_channels[105] = "extra"         # wired in the file, nothing on the card
    inst = open_lab(ports)
    with pytest.raises(InstrumentError, match=r"channel\(s\) 105 \(extra\)"):
        inst.thermometers.scan(timeout_s=2.0)
    inst.close()
    del ports.thermometer_channels[105]
    ports.thermometer_channels[141] = "beyond"        # not on a 40-channel card
    inst = open_lab(ports)
    with pytest.raises(InstrumentRejected, match=r"set-up: Parameter data out of range "
                                                 r"\[-222\]"):
        inst.thermometers.scan()
    inst.close()


def test_keithley_reports_a_queued_error_by_code_and_text(emulated, drivers, caplog):
    backing, lab = emulated
    emu = lab.emulators["thermometers"]
    drivers.thermometers.scan()
    emu.inject("error_code", code=-230, reason="Data corrupt or stale")
    with caplog.at_level(logging.WARNING):
        scan = drivers.thermometers.scan()
    assert "scan attempt 1/4 failed (InstrumentError: Data corrupt or stale)" in caplog.text
    assert len(scan.temperatures_C) == 4
    # an instrument that was reset (set-up lost) is set up again by the retry
    emu.reset()
    drivers.thermometers.scan()


def test_robot_outside_stroke_and_wrong_instrument(emulated, drivers):
    backing, lab = emulated
    with pytest.raises(InstrumentError, match=r"move_to failed 4 time\(s\).*last error: target "
                                              r"\[0.5, 0.0, 0.0\] outside the stroke \[stroke\]"):
        drivers.robot.move_to(np.array([0.5, 0.0, 0.0]))
    ports = lab.ports()
    from dataclasses import replace
    inst = open_lab(replace(ports, robot=ports.interferometers))
    with pytest.raises(InstrumentRejected, match=r"identifies as 'SIOS SP-2000,emulated,"
                                                 r"deltatwin', not a deltatwin robot controller"):
        inst.robot.read_encoders()
    inst.close()
    inst = open_lab(replace(ports, interferometer_axes=("x", "z")))
    with pytest.raises(InstrumentRejected, match=r"unit reports axes \['x', 'y'\], the ports "
                                                 r"file says \['x', 'z'\]"):
        inst.interferometers.read()
    inst.close()


def test_generic_protocol_answers_bad_checksum_and_unknown_command(emulated):
    backing, lab = emulated
    line = SerialLine(lab.emulators["coils"].url, instrument="raw", timeout_s=LINE_TIMEOUT_S)
    line.write_line("CURR?*0000")
    assert line.read_line().startswith("ERR 3 checksum mismatch*")
    from deltatwin.hw.coil_supply import PROTOCOL
    line.write_line(PROTOCOL.framing.encode("FLY 1"))
    with pytest.raises(InstrumentRejected, match=r"unknown command: FLY 1 \[1\]"):
        PROTOCOL.parse_reply("read", line.read_line(), {}, "coils")
    line.write_line(PROTOCOL.request("set", currents=(1.0, 2.0)))
    with pytest.raises(InstrumentRejected, match=r"3 currents expected, got 2 \[2\]"):
        PROTOCOL.parse_reply("set", line.read_line(), {}, "coils")
    line.close()


def test_emulated_lab_over_tcp(tmp_path):
    with EmulatedLab(toy_lab(), link="tcp", timeout_s=LINE_TIMEOUT_S, retry=FAST_RETRY) as lab:
        ports = lab.ports()
        assert ports.robot.url.startswith("socket://127.0.0.1:")
        inst = open_lab(ports)
        serial = session(inst)
        inst.close()
    assert_same(serial, session(toy_lab()), ac_tol_rad=0.05e-6)


def test_realtime_pacing_follows_the_backing_clock(tmp_path):
    """--realtime: the twin's clock is paced by the wall clock (sleep 0.3 s + a 0.5 s move of
    the toy robot take >= 0.8 s from the emulators' start); without it the same two calls take a
    few milliseconds (bounded well below the 0.8 s that pacing would impose; the set-up before
    them is not timed, so a loaded machine does not make this fail)."""
    import time
    for realtime in (True, False):
        t0 = time.monotonic()           # pacing counts from the emulators' start
        with EmulatedLab(toy_lab(), tmp_path / str(realtime), realtime=realtime,
                         timeout_s=LINE_TIMEOUT_S, retry=FAST_RETRY) as lab:
            inst = open_lab(lab.ports())
            inst.connect()
            t_calls = time.monotonic()
            inst.clock.sleep(0.3)
            inst.robot.move_to(np.array([0.01, 0.0, 0.0]))
            t_end = time.monotonic()
            assert inst.clock.now() == pytest.approx(0.8)
            inst.close()
        if realtime:
            assert 0.8 <= t_end - t0 < 10.0
        else:
            assert t_end - t_calls < 0.5, t_end - t_calls
