"""Newport LDS1000 autocollimator controllers (``Autocollimators``): one or more controllers,
two axes each (axis 1 = the autocollimator's Y, axis 2 = its Z), each axis mapped to a channel
name (e.g. ``ac1_ry``) by the ports file.

Commands (../shared/reference.md, docs/hardware.md): ``MR`` remote mode (no reply, sent first),
``VE`` -> ``VE LDS1000 Controller Version 3.10``, ``1TA`` -> ``1TA,RT,04512,1,µrad,00102,00241``
(the 5th field is the unit: µrad, sec, mrad; linear units are refused), ``1TP`` ->
``1TP-1596.3`` (the reading in that unit), ``TE`` -> ``TE@`` (last error code, cleared by
reading), ``TB`` -> ``TB<code> <text>`` (last error with its text, cleared by reading).

After every ``nTP`` the driver asks ``TE``: ``@`` = valid, ``O`` = outside the measuring range
(the angle is reported NaN with ``in_range`` False), any other code = the reading is not valid
(``InstrumentError`` with the code and its meaning; retried). Two things are assumptions, as
the public sources do not say: the controller answers ``nTP`` even when the reading is not valid
(with the error then in ``TE``), and ``TB``'s reply layout. Baud rate and terminator are
settings (ports file). Numbers have no fixed width, so a dropped digit inside a number cannot
be detected by any driver; a dropped sign, axis, point or unit letter is.
"""
from __future__ import annotations

import math

from deltatwin.hw.driver import LineInstrument
from deltatwin.hw.protocol import (
    Command,
    InstrumentRejected,
    Protocol,
    ReplyError,
    integer,
    text,
)
from deltatwin.twin.instruments.interface import (
    DEFAULT_TIMEOUT_S,
    AngleReading,
    Autocollimators,
    Clock,
    InstrumentError,
)

ERROR_CODES = {"@": "no error", "A": "unknown command", "B": "bad axis", "C": "out of limits",
               "D": "not allowed", "O": "out of range", "S": "timeout"}
REJECTED_CODES = frozenset({"A", "B"})
ARCSEC_RAD = math.pi / 648000.0
UNIT_RAD = {"µrad": 1e-6, "urad": 1e-6, "mrad": 1e-3, "sec": ARCSEC_RAD}
# decimals the controller writes in each unit (resolution 0.02 arcsec ~ 0.1 µrad)
UNIT_DECIMALS = {"µrad": 1, "urad": 1, "mrad": 4, "sec": 2}
RANGE_RAD = 400 * ARCSEC_RAD      # the LDS-1000 measures +-400 arcsec


def format_value(angle_in_unit: float, unit: str) -> str:
    """A reading as the controller writes it: the unit's fixed number of decimals."""
    return f"{angle_in_unit:.{UNIT_DECIMALS[unit]}f}"

AXIS = integer()
PROTOCOL = Protocol(
    "Newport LDS1000",
    {
        "remote": Command("MR"),
        "version": Command("VE", "VE {version}", {"version": text()}),
        "units": Command("{axis}TA", "{axis}TA,{mode},{a},{b},{unit},{c},{d}",
                         {"axis": AXIS, "mode": text(r"[^,]*"), "a": text(r"[^,]*"),
                          "b": text(r"[^,]*"), "unit": text(r"[^,]+"), "c": text(r"[^,]*"),
                          "d": text(r"[^,]*")}),
        # the reading as written, in the axis's unit with that unit's decimals (checked by the
        # driver: a lost digit after the point, or the point, changes the count)
        "position": Command("{axis}TP", "{axis}TP{value}",
                            {"axis": AXIS, "value": text(r"[+-]?\d+\.\d+|[+-]?\d+")}),
        "error_code": Command("TE", "TE{code}", {"code": text(r"[@A-Z]")}),
        "error_text": Command("TB", "TB{code} {reason}", {"code": text(r"[@A-Z]"),
                                                          "reason": text()}),
    },
    terminator="CR",
    rejected_codes=REJECTED_CODES,
)


class LDS1000(LineInstrument):
    """One controller. ``axes``: axis number (1, 2) -> channel name."""
    protocol = PROTOCOL

    def __init__(self, line, axes: dict[int, str], *, name="autocollimator",
                 max_step_rad: float | None = None, **kw):
        super().__init__(line, name=name, **kw)
        # the largest believable change of an angle between two readings (ports file
        # max_step_arcsec; None: not checked): a bigger jump is taken for a damaged reply (a
        # lost leading digit or sign) and read again; a real jump fails every attempt
        self.max_step_rad = max_step_rad
        bad = [a for a in axes if a not in (1, 2)]
        if bad or not axes:
            raise ValueError(f"{name}: LDS1000 axes must be 1 and/or 2, got {list(axes)}")
        self.axes = dict(sorted(axes.items()))
        self.scale_rad: dict[int, float] = {}
        self.unit: dict[int, str] = {}
        self.previous_rad: dict[int, float] = {}    # last accepted in-range reading per axis

    def connect(self) -> None:
        self.ask("remote")
        version = self.ask("version")["version"]
        if not version.startswith("LDS1000"):
            raise InstrumentRejected(self.name, f"{self.line.url} answers VE as {version!r}, "
                                                f"not an LDS1000")
        for axis in self.axes:
            unit = self.ask("units", axis=axis)["unit"]
            if unit not in UNIT_RAD:
                raise InstrumentRejected(self.name, f"axis {axis} is set to unit {unit!r}; "
                                                    f"set an angle unit ({', '.join(UNIT_RAD)})")
            self.scale_rad[axis] = UNIT_RAD[unit]
            self.unit[axis] = unit

    def _error(self, code: str) -> InstrumentError:
        return self.protocol.make_error(self.name, {"code": code,
                                                    "reason": ERROR_CODES.get(code, "unknown")})

    def pending_error(self) -> InstrumentError | None:
        err = self.ask("error_text")
        return None if err["code"] == "@" else self._error(err["code"])

    def _read_once(self) -> tuple[dict[str, float], dict[str, bool]]:
        angles, in_range = {}, {}
        for axis, channel in self.axes.items():
            text = self.ask("position", axis=axis)["value"]
            code = self.ask("error_code")["code"]
            if code not in ("@", "O"):
                raise self._error(code)
            in_range[channel] = code == "@"
            angles[channel] = self._plausible(axis, text) if code == "@" else math.nan
        for axis, channel in self.axes.items():          # the whole reply set was plausible
            if in_range[channel]:
                self.previous_rad[axis] = angles[channel]
        return angles, in_range

    def _plausible(self, axis: int, text: str) -> float:
        """The reading ``text`` in rad, after every check the protocol allows (no checksum, no
        fixed width): the unit's number of decimals, the measuring range, and a step from the
        previous reading below ``max_step_rad`` (when set). Raises ``ReplyError`` (retried: a new
        reading)."""
        unit = self.unit[axis]
        decimals = len(text.partition(".")[2])
        if "." not in text or decimals != UNIT_DECIMALS[unit]:
            raise ReplyError(self.name, f"axis {axis} reading {text!r} has {decimals} decimal(s);"
                                        f" the controller writes {UNIT_DECIMALS[unit]} in "
                                        f"{unit!r} (a lost byte?)")
        angle = float(text) * self.scale_rad[axis]
        if abs(angle) > RANGE_RAD * 1.001:
            raise ReplyError(self.name, f"axis {axis} reading {text} {unit} is outside the "
                                        "+-400 arcsec measuring range without error O (a lost "
                                        "byte?)")
        previous = self.previous_rad.get(axis)
        if previous is not None and self.max_step_rad is not None \
                and abs(angle - previous) > self.max_step_rad:
            raise ReplyError(self.name, f"axis {axis} reading {text} {unit} jumps "
                                        f"{abs(angle - previous) / ARCSEC_RAD:.1f} arcsec from the"
                                        f" previous one (max_step_arcsec "
                                        f"{self.max_step_rad / ARCSEC_RAD:g}; a lost digit?)")
        return angle

    def read_angles(self, timeout_s: float = DEFAULT_TIMEOUT_S):
        """(angles rad, in_range) of this controller's channels."""
        return self.operation("read", self._read_once, timeout_s)


class NewportAutocollimators(Autocollimators):
    """Every LDS1000 controller of the laboratory as one ``Autocollimators``."""

    def __init__(self, controllers: list[LDS1000], clock: Clock):
        self.controllers, self.clock = controllers, clock
        self.channels = tuple(ch for c in controllers for ch in c.axes.values())
        if len(set(self.channels)) != len(self.channels):
            raise ValueError(f"autocollimator channel names repeat: {self.channels}")

    def read(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> AngleReading:
        angles, in_range = {}, {}
        for c in self.controllers:
            a, r = c.read_angles(timeout_s)
            angles.update(a)
            in_range.update(r)
        return AngleReading(self.clock.now(), angles, in_range)

    def close(self) -> None:
        for c in self.controllers:
            c.close()
