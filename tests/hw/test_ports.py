"""The ports file: a laboratory's file loads into drivers' settings; written files read back;
every mistake is named by file, table, key and reason."""
import pytest

from deltatwin.hw.ports import LabPorts, Port, PortsFileError, load_ports, write_ports
from deltatwin.hw.retry import RetryPolicy

LAB = """\
lab = "ETH micro-nano lab"

[retry]
attempts = 6
first_delay_s = 0.1
factor = 2.0
max_delay_s = 5.0

[robot]
url = "/dev/ttyUSB0"
baud = 115200

[interferometers]
url = "socket://192.168.1.20:4000"
axes = ["x", "y"]
timeout_s = 3

[[autocollimators]]
url = "/dev/ttyS0"
terminator = "CRLF"
channels = { 1 = "ac1_ry", 2 = "ac1_rz" }

[[autocollimators]]
url = "/dev/ttyS1"
channels = { 1 = "ac2_rx", 2 = "ac2_rz" }

[thermometers]
url = "/dev/ttyUSB1"
baud = 9600
terminator = "CR"
xonxoff = true
channels = { 101 = "air_x", 102 = "air_y", 110 = "base", 201 = "arm1" }
"""


def test_a_laboratory_file_loads_with_defaults(tmp_path):
    path = tmp_path / "eth.toml"
    path.write_text(LAB)
    p = load_ports(path)
    assert p.lab == "ETH micro-nano lab"
    assert p.clock is None and p.coils is None              # wall clock, no force simulator
    assert p.retry == RetryPolicy(6, 0.1, 2.0, 5.0)
    assert p.robot == Port("/dev/ttyUSB0", 115200, "LF", 1.0)
    assert p.interferometers == Port("socket://192.168.1.20:4000", 115200, "LF", 3.0)
    assert p.interferometer_axes == ("x", "y")
    assert p.autocollimators == ((Port("/dev/ttyS0", 9600, "CRLF", 1.0),
                                  {1: "ac1_ry", 2: "ac1_rz"}),
                                 (Port("/dev/ttyS1", 9600, "CR", 1.0),
                                  {1: "ac2_rx", 2: "ac2_rz"}))
    assert p.thermometers == Port("/dev/ttyUSB1", 9600, "CR", 5.0, xonxoff=True)
    assert p.thermometer_channels == {101: "air_x", 102: "air_y", 110: "base", 201: "arm1"}
    # written back and read again: the same
    out = write_ports(tmp_path / "copy.toml", p, comment="copied\nby the test")
    assert out.read_text().startswith("# copied\n# by the test\nformat_version = 1\nlab = ")
    assert load_ports(out) == p
    assert not list(tmp_path.glob(".copy.toml.*"))          # no temporary left behind


def test_emulated_lab_ports_round_trip(emulated, tmp_path):
    backing, lab = emulated
    ports = lab.ports()
    assert isinstance(ports, LabPorts) and ports.clock is not None and ports.coils is not None
    assert load_ports(write_ports(tmp_path / "emu.toml", ports)) == ports


@pytest.mark.parametrize("edit,message", [
    (lambda t: t.replace('url = "/dev/ttyUSB0"\n', ""), r"\[robot\] url: missing"),
    (lambda t: t.replace("baud = 115200", "baud = -3"),
     r"\[robot\] baud: must be an integer in \[1, 1e\+07\], got -3"),
    (lambda t: t.replace("baud = 9600", "baud = 38400"),
     r"\[thermometers\] baud: the Keithley 2700 runs at \[300, .*19200\], got 38400"),
    (lambda t: t.replace('terminator = "CR"', 'terminator = "NUL"'),
     r"\[thermometers\] terminator: must be one of \['CR', 'CRLF', 'LF'\], got 'NUL'"),
    (lambda t: t.replace("timeout_s = 3", "timeout_s = 0"),
     r"\[interferometers\] timeout_s: must be a number of seconds in \(0, 3600\]"),
    (lambda t: t.replace("timeout_s = 3", "timeout_s = 1e300"),
     r"\[interferometers\] timeout_s: must be a number of seconds in \(0, 3600\], got 1e\+300"),
    (lambda t: t.replace('102 = "air_y"', '"0101" = "air_y"'),
     r"\[thermometers\] channels: key '0101' is channel 101 again"),
    (lambda t: t.replace("[retry]\nattempts = 6\nfirst_delay_s = 0.1\nfactor = 2.0\n"
                         "max_delay_s = 5.0\n", "retry = 5\n"),
     r"retry = 5: expected a table \[retry\]"),
    (lambda t: t.replace('[robot]\nurl = "/dev/ttyUSB0"\nbaud = 115200\n', "").replace(
        'lab = "ETH micro-nano lab"', 'lab = "ETH micro-nano lab"\nrobot = 1'),
     r"robot = 1: expected a table \[robot\]"),
    (lambda t: t.replace("110 = ", "150 = "),
     r"\[thermometers\] channels: key '150' is not a multiplexer channel \(101-140, 201-240\)"),
    (lambda t: t.replace('110 = "base"', '110 = "air_x"'),
     r"\[thermometers\] channels: name\(s\) \['air_x'\] used more than once"),
    (lambda t: t.replace('201 = "arm1"', '201 = "arm 1"'),
     r"\[thermometers\] channels.201: name 'arm 1': must be a name"),
    (lambda t: t.replace('1 = "ac2_rx"', '3 = "ac2_rx"'),
     r"\[autocollimators #2\] channels: key '3' is not an LDS1000 axis \(1, 2\)"),
    (lambda t: t.replace('"ac2_rz"', '"ac1_rz"'),
     r"\[autocollimators\] channel names repeat across controllers"),
    (lambda t: t.replace('axes = ["x", "y"]', "axes = []"),
     r"\[interferometers\] axes: missing"),
    (lambda t: t.replace("xonxoff = true", "xonxof = true"),
     r"\[thermometers\] unknown key\(s\) \['xonxof'\]"),
    (lambda t: t.replace("[robot]", "[robots]"), r"unknown key\(s\) \['robots'\]"),
    (lambda t: t.replace("attempts = 6", "attempts = 0"),
     r"\[retry\] attempts: must be an integer in \[1, 1000\], got 0"),
    (lambda t: t.replace("[thermometers]", "[thermometers"), r"not valid TOML"),
    (lambda t: t.split("[thermometers]")[0], r"\[thermometers\] missing"),
])
def test_mistakes_are_named(tmp_path, edit, message):
    path = tmp_path / "lab.toml"
    path.write_text(edit(LAB))
    with pytest.raises(PortsFileError, match=str(path).replace(".", r"\.") + ": " + message):
        load_ports(path)


def test_a_folder_is_not_a_ports_file(tmp_path):
    with pytest.raises(PortsFileError, match="is a folder"):
        load_ports(tmp_path)


def test_missing_file(tmp_path):
    with pytest.raises(PortsFileError, match="no such ports file"):
        load_ports(tmp_path / "nope.toml")


def test_a_future_format_version_is_refused(tmp_path):
    path = tmp_path / "lab.toml"
    path.write_text("format_version = 7\n" + LAB)
    with pytest.raises(PortsFileError, match="format_version = 7"):
        load_ports(path)
