"""SCPI as IEEE 488.2 / SCPI-99 say, on the Keithley emulator: the parser (hw/scpi.py), a peer
driver (PyMeasure's Keithley2700 through pyvisa-py on a real pseudo-terminal), the reading
counter past 99,999; and the emulators' refusals of well-formed invalid values."""
import time

import numpy as np
import pytest
import serial

from deltatwin.hw.emulators.keithley2700 import COMMANDS
from deltatwin.hw.protocol import CRC16
from deltatwin.hw.scpi import ScpiError

from .conftest import ARCSEC  # noqa: F401  (conftest's toy lab backs the emulators)


def parsed(line):
    units = []
    COMMANDS.parse(line, units.append)
    return [(u.command.name, u.values) for u in units]


@pytest.mark.parametrize("line", [
    "SENS:FUNC 'TEMP',(@101:103)", "sens:func 'temp',(@101:103)",
    ":SENSe:FUNCtion 'TEMPerature', (@101:103)", "FUNC \"TEMP\" , (@101 : 103)",
    "  :sense:function\t'Temp',(@101:103)  ",
])
def test_long_short_forms_case_colon_whitespace(line):
    assert parsed(line) == [("function", ("TEMPERATURE", (101, 102, 103)))]


def test_semicolons_relative_paths_and_common_commands():
    # after ROUT:SCAN:LSEL the path is ROUT:SCAN, so TSO is ROUT:SCAN:TSO; ':' goes to the root
    assert parsed("ROUT:SCAN:LSEL NONE;TSO IMM;*CLS;:TRIG:SOUR IMM;COUN 1;") == [
        ("scan_list_select", ("NONE",)), ("scan_trigger", ("IMMEDIATE",)), ("clear", ()),
        ("trigger_source", ("IMMEDIATE",)), ("trigger_count", (1,))]
    assert parsed("status:queue:clear;*RST;:stat:pres;:*CLS;") == [
        ("clear_queue", ()), ("reset", ()), ("status_preset", ()), ("clear", ())]
    assert parsed("SYST:ERR?;:syst:err:next?") == [("error", ()), ("error", ())]


@pytest.mark.parametrize("line, code", [
    ("ROUT:SCAN:BOGUS", -113), ("SCAN:LSEL NONE", -113),      # relative to the root: undefined
    ("ROUT:SCAN:LSEL MAYBE", -224), ("TRIG:COUN 0", -222), ("TRIG:COUN x", -104),
    ("ROUT:SCAN", -109), ("*CLS 1", -108), ("ROUT:SCAN (@101:1x3)", -224),
    ("ROUT::SCAN (@101)", -102), ("SENS:FUNC TEMP", -224),
])
def test_parser_errors_are_standard_codes(line, code):
    with pytest.raises(ScpiError) as err:
        parsed(line)
    assert err.value.code == code


def raw(url, terminator=b"\n"):
    return serial.serial_for_url(url, baudrate=19200, timeout=2.0)


def ask(port, text, terminator=b"\n"):
    port.write(text.encode("latin-1") + terminator)
    return port.read_until(terminator).decode("latin-1").rstrip("\r\n")


def test_keithley_emulator_chained_queries_errors_and_crlf(emulated):
    backing, lab = emulated
    with raw(lab.emulators["thermometers"].url) as port:
        assert ask(port, "*idn?\r").startswith("KEITHLEY INSTRUMENTS INC.,MODEL 2700,")
        # a bad header stops its line (the *OPC? after it is discarded), the error is queued
        port.write(b"*CLS\nNOPE;*OPC?\n")
        assert ask(port, "*STB?;*OPC?") == "4;1"
        assert ask(port, ":SYSTem:ERRor:NEXT?") == '-113,"Undefined header"'
        assert ask(port, "SYST:ERR?") == '0,"No error"'
        assert ask(port, "*OPT?") == "7702,7702"
        assert ask(port, "FORM:ELEM READ, CHAN;:FORM:ELEM?") == "READ,CHAN"


def test_pymeasure_keithley2700_drives_the_emulator(emulated):
    """A peer driver, unchanged: PyMeasure's Keithley2700 through pyvisa-py (``@py``) on the
    emulator's pseudo-terminal; identification, reset, error queue and the manual's 4-wire PT100
    scan give the backing's temperatures."""
    from pymeasure.adapters import VISAAdapter
    from pymeasure.instruments.keithley import Keithley2700
    backing, lab = emulated
    emu = lab.emulators["thermometers"]
    device = emu.link.device                                   # /dev/pts/N
    adapter = VISAAdapter(f"ASRL{device}::INSTR", visa_library="@py", baud_rate=19200,
                          read_termination="\n", write_termination="\n", timeout=3000)
    k = Keithley2700(adapter)          # its constructor asks SYST:ERR? and *OPT?
    try:
        assert k.id.startswith("KEITHLEY INSTRUMENTS INC.,MODEL 2700,")
        assert k.options == ["7702", "7702"]
        k.write("NOT:A:COMMAND")
        errors = k.check_errors()
        assert [int(e[0]) for e in errors] == [-113]
        k.reset()                                              # status:queue:clear;*RST;...
        assert k.check_errors() == []
        k.open_all_channels()
        assert k.closed_channels == []
        assert k.complete == "1"
        # the manual's 4-wire PT100 scan (reference.md), long and short forms mixed
        chans = "(@101:104)"
        for cmd in ["ROUT:SCAN:LSEL NONE", f"SENS:FUNC 'TEMP',{chans}",
                    f":SENSe:TEMPerature:TRANsducer FRTD, {chans}",
                    f"sens:temp:frtd:type PT100,{chans}", "INIT:CONT OFF", "TRIG:SOUR IMM",
                    "TRIG:COUN 1", f"ROUT:SCAN {chans}", "SAMP:COUN 4", "ROUT:SCAN:TSO IMM",
                    "FORM:ELEM READ"]:
            k.write(cmd)
        assert k.check_errors() == []
        k.write("ROUT:SCAN:LSEL INT")
        temps = k.values("READ?")
        k.write("ROUT:SCAN:LSEL NONE")
        assert k.check_errors() == []
        # the toy lab's sensors: 20 degC + 1e-3 * t + (0.1, 0.2, 0.3, 0.4) + noise 1e-3
        t = backing.clock.now()
        np.testing.assert_allclose(temps, 20.0 + 1e-3 * t + np.array([0.1, 0.2, 0.3, 0.4]),
                                   atol=0.01)
    finally:
        k.adapter.close()


def test_pymeasure_scan_after_reset_reads_without_init_cont_off(emulated):
    """The Model 2700 manual (section 8, "Idle"): *RST restores the one-shot mode (continuous
    initiation OFF); power-on (the factory default setup) and SYSTem:PRESet leave it ON. So
    PyMeasure's Keithley2700 reset, the PT100 set-up, a scan list, TSO IMM, LSEL INT and READ?
    read the scan with no INIT:CONT OFF sent, and no error is queued."""
    from pymeasure.adapters import VISAAdapter
    from pymeasure.instruments.keithley import Keithley2700
    backing, lab = emulated
    emu = lab.emulators["thermometers"]
    adapter = VISAAdapter(f"ASRL{emu.link.device}::INSTR", visa_library="@py", baud_rate=19200,
                          read_termination="\n", write_termination="\n", timeout=3000)
    k = Keithley2700(adapter)
    try:
        assert k.ask("INIT:CONT?").strip() == "1"              # power-on: factory defaults
        k.reset()                                              # status:queue:clear;*RST;...
        assert k.ask("INIT:CONT?").strip() == "0"
        chans = "(@101:103)"
        for cmd in [f"SENS:FUNC 'TEMP',{chans}", f"SENS:TEMP:TRAN FRTD,{chans}",
                    f"SENS:TEMP:FRTD:TYPE PT100,{chans}", f"ROUT:SCAN {chans}",
                    "ROUT:SCAN:TSO IMM", "ROUT:SCAN:LSEL INT", "FORM:ELEM READ"]:
            k.write(cmd)
        temps = k.values("READ?")
        assert len(temps) == 3
        t = backing.clock.now()
        np.testing.assert_allclose(temps, 20.0 + 1e-3 * t + np.array([0.1, 0.2, 0.3]),
                                   atol=0.01)
        assert k.check_errors() == []
        k.write("SYST:PRES")
        assert k.ask("INIT:CONT?").strip() == "1"
        assert k.ask("ROUT:SCAN?").strip() == "(@)"           # the set-up is lost
    finally:
        k.adapter.close()


def test_reading_counter_past_99999(emulated, drivers):
    """The reading number grows past 5 digits (+100001RDNG#); the driver keeps reading."""
    backing, lab = emulated
    emu = lab.emulators["thermometers"]
    drivers.thermometers.scan()
    emu.readings_taken = 99_998
    for _ in range(3):
        scan = drivers.thermometers.scan()
        assert len(scan.temperatures_C) == 4
    assert emu.readings_taken == 99_998 + 12
    assert "+100010RDNG#" in emu.last_reply


def test_keithley_dropped_digit_in_a_long_reading_number_is_detected():
    from deltatwin.hw.keithley2700 import PROTOCOL, format_reading
    line = ",".join(format_reading(20.0 + k, 1.0, 123_456 + k, 101 + k) for k in range(3))
    readings = PROTOCOL.parse_reply("read", line, {}, "k")["readings"]
    assert [n for _, _, n in readings] == [123456, 123457, 123458]
    for i in [line.index("123457") + 2, line.index("123456") + 1]:
        damaged = PROTOCOL.parse_reply("read", line[:i] + line[i + 1:], {}, "k")["readings"]
        numbers = [n for _, _, n in damaged]
        assert numbers != list(range(numbers[0], numbers[0] + 3))   # what the driver refuses


def generic_ask(port, payload):
    port.write(CRC16.encode(payload).encode() + b"\n")
    line = port.read_until(b"\n").decode().rstrip("\n")
    reply = CRC16.decode(line)
    assert reply is not None, line
    return reply


@pytest.mark.parametrize("instrument, request_, words", [
    ("coils", "CURR nan nan nan", ["ERR 2 bad argument", "finite"]),
    ("coils", "CURR 1 inf 0", ["ERR 2 bad argument", "finite"]),
    ("coils", "CURR abc", ["ERR 2 bad argument"]),
    ("robot", "MOVE nan 0 0", ["ERR 2 bad argument", "finite"]),
    ("clock", "SLEEP -1000", ["ERR 2 bad argument", ">= 0"]),
    ("clock", "SLEEP nan", ["ERR 2 bad argument"]),
    ("clock", "SLEEP soon", ["ERR 2 bad argument"]),
    ("clock", "SLEPE 1", ["ERR 1 unknown command"]),
])
def test_generic_emulators_refuse_invalid_values(emulated, instrument, request_, words):
    backing, lab = emulated
    t0 = backing.clock.now()
    with raw(lab.emulators[instrument].url) as port:
        reply = generic_ask(port, request_)
        for w in words:
            assert w in reply, reply
        assert generic_ask(port, "CURR?" if instrument == "coils" else "*IDN?")
    assert backing.clock.now() == t0            # time did not run backwards (or at all)
    assert np.all(np.isfinite(backing.coils.currents))


def test_long_lines_are_refused_fast_and_buffers_bounded(emulated):
    backing, lab = emulated
    with raw(lab.emulators["coils"].url) as port:
        start = time.monotonic()
        reply = generic_ask(port, "CURR " + "1" * 10_000)
        assert "ERR 2 bad argument: request longer than 255 characters" in reply
        port.write(b"2" * 5000)                   # no terminator: dropped, not accumulated
        time.sleep(0.1)
        assert len(lab.emulators["coils"]._buffer) <= 255
        reply = generic_ask(port, "CURR?")        # the dropped line ends here, refused
        assert "longer than 255" in reply
        assert generic_ask(port, "CURR?").startswith("CURR ")
        elapsed = time.monotonic() - start
    with raw(lab.emulators["thermometers"].url) as port:
        port.write(b"*CLS\n" + b"X" * 300 + b"\n")
        assert ask(port, "SYST:ERR?") == '-363,"Input buffer overrun"'
    assert elapsed < 2.0, elapsed              # was 3.5 s for one 10 kB line (quadratic regex)


def test_real_number_field_parses_a_long_line_in_linear_time():
    from deltatwin.hw.coil_supply import PROTOCOL
    for n in (2_000, 20_000):
        start = time.monotonic()
        assert PROTOCOL.parse_request(CRC16.encode("CURR " + "1" * n + " x")) is None
        elapsed = time.monotonic() - start
        assert elapsed < 0.5, (n, elapsed)


def test_simulated_clock_refuses_bad_sleeps_without_naming_unknown_keys():
    from deltatwin.twin.instruments.simulated import SimulatedLab
    from deltatwin.twin.scenario import Scenario
    sc = Scenario.load("paper-thermal")
    twin, _ = sc.build(0.0003)
    clock = SimulatedLab(twin, sc.settings).instrument_set().clock
    for bad in (-1000.0, float("nan"), 1e9):
        with pytest.raises(ValueError) as err:
            clock.sleep(bad)
        assert "horizon_s" not in str(err.value) and "clock" in str(err.value)
    assert clock.now() == 0.0
