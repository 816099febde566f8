"""The ports file (TOML, one per laboratory): where each instrument is and how to talk to it.

Layout (docs/hardware.md has the full description and an example)::

    lab = "ETH micro-nano lab"
    [retry]                     # optional: bounded back-off of every driver
    attempts = 5
    first_delay_s = 0.05
    factor = 2.0
    max_delay_s = 2.0
    [clock]                     # optional: absent = the wall clock (a real laboratory)
    url = "/tmp/emu/clock"
    [robot]
    url = "/dev/ttyUSB0"        # device path, symlink, or pyserial URL (socket://host:port)
    baud = 115200               # optional, per-instrument default
    terminator = "LF"           # optional: LF, CR or CRLF
    timeout_s = 1.0             # optional: longest wait for one reply line
    xonxoff = false             # optional: software flow control by the OS
    [interferometers]
    url = "..."
    axes = ["x", "y"]
    [[autocollimators]]         # one table per LDS1000 controller
    url = "..."
    channels = { 1 = "ac1_ry", 2 = "ac1_rz" }
    [thermometers]
    url = "..."
    channels = { 101 = "air_x", 102 = "base" }
    [coils]                     # optional: only where the force simulator is fitted
    url = "..."
    n_coils = 3

``load_ports`` validates everything and names the file, the key and the reason on any problem;
``write_ports`` writes the same layout atomically.
"""
from __future__ import annotations

import math
import os
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

from deltatwin.files import atomic_write_text, toml_text
from deltatwin.hw.protocol import TERMINATORS
from deltatwin.hw.retry import RetryPolicy

# per instrument: (default baud, default terminator, default timeout_s)
DEFAULTS = {
    "clock": (115200, "LF", 2.0),
    "robot": (115200, "LF", 1.0),
    "interferometers": (115200, "LF", 2.0),
    "autocollimators": (9600, "CR", 1.0),
    "thermometers": (19200, "LF", 5.0),
    "coils": (9600, "LF", 1.0),
}
FORMAT_VERSION = 1          # of the ports files written here (and read: a laboratory's may omit it)
MAX_TIMEOUT_S = 3600.0      # longer is no reply wait but a hang (and overflows serial timeouts)
PORT_KEYS = ("url", "baud", "terminator", "timeout_s", "xonxoff")
EXTRA_KEYS = {"clock": (), "robot": (), "interferometers": ("axes",),
              "autocollimators": ("channels", "max_step_arcsec"), "thermometers": ("channels",),
              "coils": ("n_coils",)}
NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
KEITHLEY_BAUDS = (300, 600, 1200, 2400, 4800, 9600, 19200)


class PortsFileError(ValueError):
    """A ports file that cannot be used; the message names the file, the key and the reason."""


@dataclass(frozen=True)
class Port:
    url: str
    baud: int
    terminator: str
    timeout_s: float
    xonxoff: bool = False


@dataclass(frozen=True)
class LabPorts:
    lab: str
    robot: Port
    interferometers: Port
    interferometer_axes: tuple[str, ...]
    autocollimators: tuple[tuple[Port, dict[int, str]], ...]
    thermometers: Port
    thermometer_channels: dict[int, str]
    clock: Port | None = None
    coils: Port | None = None
    n_coils: int = 3
    retry: RetryPolicy = RetryPolicy()
    # per [[autocollimators]] table: the largest believable change of an angle between two
    # readings (arcsec), None = not checked
    autocollimator_max_step_arcsec: tuple[float | None, ...] = ()


def _fail(path, where: str, reason: str):
    raise PortsFileError(f"{path}: [{where}] {reason}")


# [retry] key -> (integer, lowest, highest): bounded, so that a campaign's wait stays finite
RETRY_RANGES = {"attempts": (True, 1, 1000), "first_delay_s": (False, 0.0, MAX_TIMEOUT_S),
                "factor": (False, 1.0, 100.0), "max_delay_s": (False, 0.0, MAX_TIMEOUT_S)}
MAX_BAUD = 10_000_000       # above any serial line's rate
MAX_COILS = 64


def _check_number(path, where: str, key: str, value, low, high, integer: bool = False):
    kind = "an integer" if integer else "a number"
    if isinstance(value, bool) or not isinstance(value, int if integer else (int, float)) \
            or not math.isfinite(value) or not low <= value <= high:
        _fail(path, where, f"{key}: must be {kind} in [{low:g}, {high:g}], got {value!r}")
    return value


def _port(path, where: str, kind: str, table) -> Port:
    if not isinstance(table, dict):
        _fail(path, where, f"must be a table, got {type(table).__name__}")
    unknown = sorted(set(table) - set(PORT_KEYS) - set(EXTRA_KEYS[kind]))
    if unknown:
        _fail(path, where, f"unknown key(s) {unknown}; allowed: "
                           f"{list(PORT_KEYS) + list(EXTRA_KEYS[kind])}")
    baud, terminator, timeout_s = DEFAULTS[kind]
    url = table.get("url")
    if not isinstance(url, str) or not url:
        _fail(path, where, "url: missing (a device path such as /dev/ttyUSB0, or "
                           "socket://host:port)")
    baud = _check_number(path, where, "baud", table.get("baud", baud), 1, MAX_BAUD, integer=True)
    if kind == "thermometers" and baud not in KEITHLEY_BAUDS:
        _fail(path, where, f"baud: the Keithley 2700 runs at {list(KEITHLEY_BAUDS)}, got {baud}")
    terminator = table.get("terminator", terminator)
    if not isinstance(terminator, str) or terminator not in TERMINATORS:
        _fail(path, where, f"terminator: must be one of {sorted(TERMINATORS)}, got "
                           f"{terminator!r}")
    timeout_s = table.get("timeout_s", timeout_s)
    if (not isinstance(timeout_s, (int, float)) or isinstance(timeout_s, bool)
            or not math.isfinite(timeout_s) or not 0 < timeout_s <= MAX_TIMEOUT_S):
        _fail(path, where, f"timeout_s: must be a number of seconds in (0, {MAX_TIMEOUT_S:g}], "
                           f"got {timeout_s!r}")
    xonxoff = table.get("xonxoff", False)
    if not isinstance(xonxoff, bool):
        _fail(path, where, f"xonxoff: must be true or false, got {xonxoff!r}")
    return Port(url, baud, terminator, float(timeout_s), xonxoff)


def _names(path, where: str, names, what: str) -> None:
    for n in names:
        if not isinstance(n, str) or not NAME.fullmatch(n):
            _fail(path, where, f"{what} {n!r}: must be a name (letter, then letters, digits, _)")


def _channel_map(path, where: str, table, valid, what: str) -> dict[int, str]:
    if not isinstance(table, dict) or not table:
        _fail(path, where, "channels: missing or empty (a table channel = \"sensor name\")")
    out = {}
    for key, name in table.items():
        if not re.fullmatch(r"\d+", key) or not valid(int(key)):
            _fail(path, where, f"channels: key {key!r} is not {what}")
        if int(key) in out:
            _fail(path, where, f"channels: key {key!r} is channel {int(key)} again")
        _names(path, where, [name], f"channels.{key}: name")
        out[int(key)] = name
    if len(set(out.values())) != len(out):
        dup = sorted({n for n in out.values() if list(out.values()).count(n) > 1})
        _fail(path, where, f"channels: name(s) {dup} used more than once")
    return dict(sorted(out.items()))


def load_ports(path: str | os.PathLike) -> LabPorts:
    path = Path(path)
    if not path.exists():
        raise PortsFileError(f"{path}: no such ports file")
    if path.is_dir():
        raise PortsFileError(f"{path}: is a folder, not a ports file")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise PortsFileError(f"{path}: not valid TOML: {exc}") from exc
    version = doc.pop("format_version", FORMAT_VERSION)     # a laboratory's own file may omit it
    if not isinstance(version, int) or isinstance(version, bool) or version > FORMAT_VERSION:
        raise PortsFileError(f"{path}: format_version = {version!r}; this deltatwin reads ports "
                             f"files up to version {FORMAT_VERSION}")
    known = {"lab", "retry", *DEFAULTS}
    unknown = sorted(set(doc) - known)
    if unknown:
        raise PortsFileError(f"{path}: unknown key(s) {unknown}; allowed: {sorted(known)}")
    for required in ("robot", "interferometers", "autocollimators", "thermometers"):
        if required not in doc:
            raise PortsFileError(f"{path}: [{required}] missing")
    for key, value in doc.items():
        tables = value if key == "autocollimators" and isinstance(value, list) else [value]
        if key != "lab" and not all(isinstance(t, dict) for t in tables):
            raise PortsFileError(f"{path}: {key} = {value!r}: expected a table"
                                 + (" per controller ([[autocollimators]])"
                                    if key == "autocollimators" else f" [{key}]"))
    lab = doc.get("lab", path.stem)
    if not isinstance(lab, str):
        raise PortsFileError(f"{path}: lab: must be a string, got {lab!r}")

    retry = RetryPolicy()
    if "retry" in doc:
        r = doc["retry"]
        bad = sorted(set(r) - {"attempts", "first_delay_s", "factor", "max_delay_s"})
        if bad:
            _fail(path, "retry", f"unknown key(s) {bad}")
        for key, (integer, low, high) in RETRY_RANGES.items():
            if key in r:
                _check_number(path, "retry", key, r[key], low, high, integer)
        retry = RetryPolicy(**r)

    ifm = doc["interferometers"]
    axes = ifm.get("axes") if isinstance(ifm, dict) else None
    if not isinstance(axes, list) or not axes:
        _fail(path, "interferometers", "axes: missing (a list such as [\"x\", \"y\"])")
    _names(path, "interferometers", axes, "axes: axis")

    acs = doc["autocollimators"]
    if not isinstance(acs, list) or not acs:
        _fail(path, "autocollimators", "must be one or more [[autocollimators]] tables")
    controllers, max_steps = [], []
    for k, table in enumerate(acs):
        where = f"autocollimators #{k + 1}"
        port = _port(path, where, "autocollimators", table)
        step = table.get("max_step_arcsec")
        if step is not None and (isinstance(step, bool) or not isinstance(step, (int, float))
                                 or not 0 < step <= 800):
            _fail(path, where, f"max_step_arcsec: must be a number in (0, 800], got {step!r}")
        max_steps.append(None if step is None else float(step))
        controllers.append((port, _channel_map(path, where, table.get("channels"),
                                               lambda a: a in (1, 2), "an LDS1000 axis (1, 2)")))
    names = [n for _, ch in controllers for n in ch.values()]
    if len(set(names)) != len(names):
        _fail(path, "autocollimators", f"channel names repeat across controllers: {names}")

    th = doc["thermometers"]
    channels = _channel_map(path, "thermometers", th.get("channels") if isinstance(th, dict)
                            else None, lambda c: c // 100 in (1, 2) and 1 <= c % 100 <= 40,
                            "a multiplexer channel (101-140, 201-240)")
    coils, n_coils = None, 3
    if "coils" in doc:
        coils = _port(path, "coils", "coils", doc["coils"])
        n_coils = _check_number(path, "coils", "n_coils", doc["coils"].get("n_coils", 3), 1,
                                MAX_COILS, integer=True)
    return LabPorts(
        lab=lab,
        robot=_port(path, "robot", "robot", doc["robot"]),
        interferometers=_port(path, "interferometers", "interferometers", ifm),
        interferometer_axes=tuple(axes),
        autocollimators=tuple(controllers),
        autocollimator_max_step_arcsec=tuple(max_steps),
        thermometers=_port(path, "thermometers", "thermometers", th),
        thermometer_channels=channels,
        clock=_port(path, "clock", "clock", doc["clock"]) if "clock" in doc else None,
        coils=coils, n_coils=n_coils, retry=retry)


def _port_table(port: Port, **extra) -> dict:
    table = {"url": port.url, "baud": port.baud, "terminator": port.terminator,
             "timeout_s": port.timeout_s}
    if port.xonxoff:
        table["xonxoff"] = True
    return table | extra


def format_ports(ports: LabPorts, comment: str = "") -> str:
    r = ports.retry
    doc: dict = {"format_version": FORMAT_VERSION, "lab": ports.lab,
                 "retry": {"attempts": r.attempts, "first_delay_s": r.first_delay_s,
                           "factor": r.factor, "max_delay_s": r.max_delay_s}}
    if ports.clock is not None:
        doc["clock"] = _port_table(ports.clock)
    doc["robot"] = _port_table(ports.robot)
    doc["interferometers"] = _port_table(ports.interferometers,
                                         axes=list(ports.interferometer_axes))
    steps = ports.autocollimator_max_step_arcsec or (None,) * len(ports.autocollimators)
    doc["autocollimators"] = [
        _port_table(port, channels=axes, **({} if step is None else {"max_step_arcsec": step}))
        for (port, axes), step in zip(ports.autocollimators, steps)]
    doc["thermometers"] = _port_table(ports.thermometers, channels=ports.thermometer_channels)
    if ports.coils is not None:
        doc["coils"] = _port_table(ports.coils, n_coils=ports.n_coils)
    return toml_text(doc, comment)


def write_ports(path: str | os.PathLike, ports: LabPorts, comment: str = "") -> Path:
    """Write ``ports`` as TOML, atomically (temporary file in the same folder, then rename)."""
    return atomic_write_text(path, format_ports(ports, comment))
