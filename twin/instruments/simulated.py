"""The twin's simulated instruments: the common interface over one shared ``Twin``.

They share a simulated clock and the campaign's Schedule (moves take time and heat the
motors, coil currents heat the coils), so time advances as the campaign runs.  Noise comes
from per-instrument streams consumed in a fixed layout (``NoiseBank``): the k-th reading window
always gets the k-th draws, so the vectorised fast path (twin/campaign.py) and a campaign run
call by call through this interface (or through serial emulators) give the same data.
Instrument models (``InstrumentSettings``):
* interferometers: reading = (n s - n0 s0) / n_comp (twin/instruments/optics.py) + slow air
  turbulence (the noise floor, std per reading) + the mean of the window's white samples;
  the window's sample std is the acceptance statistic; resolution 1.24 nm;
* autocollimators: face tilts + noise, 0.02 arcsec resolution, out of range flagged;
* thermometers: PT100 sensor nodes of the thermal network (lag, missed gradients) scanned every
  period, + noise, resolution; a scan returns the latest completed one;
* barometer and hygrometer (only where the scenario's laboratory has them: ``barometer``,
  ``hygrometer``; the papers' had neither): the room's pressure and the relative humidity of the
  air by the beams (the water vapour of the room over the saturation pressure at the beams' mean
  air temperature) + noise, resolution, measured with every temperature scan (same timing).
  Defaults from a Vaisala PTB330 class A barometer (resolution 0.1 Pa; repeatability +-3 Pa,
  read as 2 sigma: 1.5 Pa std; its +-10 Pa accuracy is an offset, second order for a reading
  relative to its zero) and a Vaisala HMT330 hygrometer (resolution 0.1 %RH; +-1 %RH accuracy,
  an offset likewise; 0.2 %RH short-term noise).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from deltatwin.twin.instruments.interface import (
    AngleReading,
    Autocollimators,
    Barometer,
    Clock,
    CoilSupply,
    HumidityReading,
    Hygrometer,
    InstrumentError,
    InstrumentSet,
    InterferometerReading,
    Interferometers,
    PressureReading,
    Robot,
    TemperatureScan,
    ThermometerScanner,
)
from deltatwin.twin.instruments.optics import AC_CHANNELS, AXES
from deltatwin.twin.noise import NoiseBank
from deltatwin.twin.world import Schedule, Twin

ARCSEC = np.pi / (180.0 * 3600.0)


@dataclass(frozen=True)
class InstrumentSettings:
    """Instrument behaviour and timing (SI units; scenario table [instruments])."""
    noise_floor_m: float = 5e-9           # std of a reading (slow air turbulence)
    sample_noise_m: float = 6e-9          # median std of the samples inside a window
    sample_noise_spread: float = 0.25     # log-normal spread of that std between windows
    samples_per_window: int = 4096
    window_s: float = 0.2
    std_limit_m: float = 10e-9            # a window is accepted when every axis' std is below
    max_rereads: int = 20
    resolution_m: float = 1.24e-9
    ac_noise_rad: float = 0.03 * ARCSEC
    ac_resolution_rad: float = 0.02 * ARCSEC
    ac_range_rad: float = 400.0 * ARCSEC
    ac_read_s: float = 0.3
    T_noise_C: float = 0.003
    T_resolution_C: float = 0.001
    scan_period_s: float = 10.0
    move_base_s: float = 1.0              # settle time of every move
    speed_rad_s: float = 0.05             # actuator speed
    coil_settle_s: float = 1.0
    wait_s: float = 5.0                   # the papers' wait after a move
    overhead_s: float = 1.5               # logging, correction, temperature read-out per point
    session_gap_s: float = 1800.0         # re-arranging the optics between sessions
    barometer: bool = False               # the laboratory records the pressure (papers: no)
    barometer_noise_Pa: float = 1.5
    barometer_resolution_Pa: float = 0.1
    hygrometer: bool = False              # the laboratory records the humidity (papers: no)
    hygrometer_noise_pct: float = 0.2
    hygrometer_resolution_pct: float = 0.1

    # the physically meaningful range of each setting: (lowest, highest, lowest allowed itself);
    # a scenario outside it is refused (a zero speed divides by zero, a zero range reads NaN,
    # a zero resolution is a perfect instrument, allowed;
    # a zero acceptance limit never accepts a window, a 1e12 s gap allocates terabytes)
    RANGES: ClassVar[dict] = {
        "noise_floor_m": (0.0, 1e-6, True), "sample_noise_m": (0.0, 1e-6, True),
        "sample_noise_spread": (0.0, 3.0, True), "samples_per_window": (1, 10**6, True),
        "window_s": (0.0, 60.0, False), "std_limit_m": (0.0, 1e-6, False),
        "max_rereads": (0, 1000, True), "resolution_m": (0.0, 1e-6, True),
        "ac_noise_rad": (0.0, 1e-3, True), "ac_resolution_rad": (0.0, 1e-3, True),
        "ac_range_rad": (0.0, 0.1, False), "ac_read_s": (0.0, 60.0, True),
        "T_noise_C": (0.0, 1.0, True), "T_resolution_C": (0.0, 1.0, True),
        "scan_period_s": (0.0, 3600.0, False), "move_base_s": (0.0, 600.0, True),
        "speed_rad_s": (0.0, 10.0, False), "coil_settle_s": (0.0, 600.0, True),
        "wait_s": (0.0, 3600.0, True), "overhead_s": (0.0, 600.0, True),
        "session_gap_s": (0.0, 7 * 86400.0, True),
        "barometer_noise_Pa": (0.0, 1000.0, True), "barometer_resolution_Pa": (0.0, 1000.0, True),
        "hygrometer_noise_pct": (0.0, 20.0, True), "hygrometer_resolution_pct": (0.0, 20.0, True),
    }
    SWITCHES: ClassVar[tuple] = ("barometer", "hygrometer")   # true / false in a scenario

    def move_time(self, dq) -> float:
        return self.move_base_s + float(np.max(np.abs(dq))) / self.speed_rad_s


def interferometer_bank(rng, s: InstrumentSettings) -> NoiseBank:
    """Per window and axis (x, y, z): slow noise (m), window-mean white noise (m), sample std (m)."""
    def draw(g, n):
        slow = s.noise_floor_m * g.standard_normal((n, 3))
        sigma = s.sample_noise_m * np.exp(s.sample_noise_spread * g.standard_normal((n, 3)))
        mean = sigma / np.sqrt(s.samples_per_window) * g.standard_normal((n, 3))
        std = sigma * np.sqrt(g.chisquare(s.samples_per_window - 1, (n, 3))
                              / (s.samples_per_window - 1))
        return np.stack([slow + mean, std], axis=1)            # (n, 2, 3)
    return NoiseBank(rng, draw)


def autocollimator_bank(rng, s: InstrumentSettings) -> NoiseBank:
    return NoiseBank(rng, lambda g, n: s.ac_noise_rad * g.standard_normal((n, len(AC_CHANNELS))))


def quantize(x, step):
    """``x`` rounded to the resolution ``step`` (unchanged for a perfect instrument, step 0)."""
    return np.round(np.asarray(x) / step) * step if step > 0 else np.asarray(x)


def scan_temperatures(twin: Twin, s: InstrumentSettings, bank: NoiseBank, sensors, scan_index):
    """Readings (n, n_sensors) degC of the scans ``scan_index`` (n,) (scan k completes at k*period)."""
    scan_index = np.asarray(scan_index)
    T = twin.node_temperatures(scan_index * s.scan_period_s)
    noise = bank.take(0, int(scan_index.max()) + 1)[scan_index]
    true = np.stack([T[f"sensor:{name}"] for name in sensors], axis=1)
    return quantize(true + noise, s.T_resolution_C)


def thermometer_bank(rng, s: InstrumentSettings, n_sensors: int) -> NoiseBank:
    return NoiseBank(rng, lambda g, n: s.T_noise_C * g.standard_normal((n, n_sensors)))


def air_sensor_bank(rng, s: InstrumentSettings) -> NoiseBank:
    """Per scan: the barometer's (Pa) and the hygrometer's (%RH) noise."""
    return NoiseBank(rng, lambda g, n: g.standard_normal((n, 2))
                     * [s.barometer_noise_Pa, s.hygrometer_noise_pct])


def air_sensor_readings(twin: Twin, s: InstrumentSettings, bank: NoiseBank, scan_index) -> dict:
    """The laboratory's air records at the scans ``scan_index`` (n,), taken with the temperature
    scans: ``{"p_Pa": (n,), "RH_pct": (n,)}``, each present where the laboratory has its
    instrument (empty without a barometer or hygrometer)."""
    scan_index = np.asarray(scan_index)
    out = {}
    if not (s.barometer or s.hygrometer):
        return out
    t = scan_index * s.scan_period_s
    noise = bank.take(0, int(scan_index.max()) + 1)[scan_index]
    air = twin.air(t)
    if s.barometer:
        out["p_Pa"] = quantize(air["pressure_Pa"] + noise[:, 0], s.barometer_resolution_Pa)
    if s.hygrometer:
        out["RH_pct"] = quantize(air["humidity_pct"] + noise[:, 1], s.hygrometer_resolution_pct)
    return out


def interferometer_values(optical_path_m, n_comp, zero_path, axes, noise_row,
                          s: InstrumentSettings):
    """Displacements (n, len(axes)) m and window stds from the optical paths and compensation
    indices by axis ((n,) each), the zero's paths and the windows' noise rows."""
    vals, stds = [], []
    for a in axes:
        k = AXES.index(a)
        geo = (optical_path_m[a] - zero_path[a]) / n_comp[a]
        vals.append(quantize(geo + noise_row[:, 0, k], s.resolution_m))
        stds.append(noise_row[:, 1, k])
    return np.stack(vals, axis=1), np.stack(stds, axis=1)


def autocollimator_values(truth, noise_row, s: InstrumentSettings):
    """Angles (n,4) rad (NaN where out of range) and the in-range flags."""
    ang = np.stack([truth.angles_rad[c] for c in AC_CHANNELS], axis=1) + noise_row
    ok = np.abs(ang) <= s.ac_range_rad
    return np.where(ok, quantize(ang, s.ac_resolution_rad), np.nan), ok


class SimulatedLab:
    """State shared by the simulated instruments: the twin, the clock, what the robot and coils
    are doing, and the noise banks with their counters."""

    def __init__(self, twin: Twin, settings: InstrumentSettings, axes=AXES):
        self.twin, self.s, self.axes = twin, settings, tuple(axes)
        self.t = 0.0
        self.q = np.zeros(3)
        self.currents = np.zeros(3)
        self.schedule = Schedule()
        self.ifm_bank = interferometer_bank(twin.rng["interferometers"], settings)
        self.ac_bank = autocollimator_bank(twin.rng["autocollimators"], settings)
        self.sensors = tuple(twin.sensors)
        self.T_bank = thermometer_bank(twin.rng["thermometers"], settings, len(self.sensors))
        self.air_bank = air_sensor_bank(twin.rng["air_sensors"], settings)
        self.windows = 0
        self.ac_reads = 0
        self.zero_path = {a: 0.0 for a in AXES}

    def truth_now(self, t):
        self.twin.advance(t, self.schedule)
        return self.twin.truth(self.twin.points([t], self.q[None], self.currents[None]))

    def instrument_set(self) -> InstrumentSet:
        return InstrumentSet(clock=SimClock(self), robot=SimRobot(self),
                             interferometers=SimInterferometers(self),
                             autocollimators=SimAutocollimators(self),
                             thermometers=SimThermometers(self), coils=SimCoils(self),
                             barometer=SimBarometer(self) if self.s.barometer else None,
                             hygrometer=SimHygrometer(self) if self.s.hygrometer else None)

    def air_record(self, column: str) -> tuple[float, float]:
        """(time of the latest completed scan, its air record ``column``)."""
        k = int(np.floor(self.t / self.s.scan_period_s))
        self.twin.advance(self.t, self.schedule)
        return k * self.s.scan_period_s, float(
            air_sensor_readings(self.twin, self.s, self.air_bank, np.array([k]))[column][0])


class SimClock(Clock):
    def __init__(self, lab):
        self.lab = lab

    def now(self):
        return self.lab.t

    def sleep(self, seconds):
        s = float(seconds)
        horizon = self.lab.twin.t_grid[-1]
        if not (np.isfinite(s) and s >= 0):
            raise ValueError(f"clock: sleep must be a finite number of seconds >= 0, got {s!r}")
        if self.lab.t + s > horizon:
            raise ValueError(f"clock: sleeping {s:g} s would take the simulated world to "
                             f"{self.lab.t + s:.6g} s, past the end of its time ({horizon:.6g} s, "
                             "the longest campaign its scenario, scale and seed plan for)")
        self.lab.t += s


class SimRobot(Robot):
    def __init__(self, lab):
        self.lab = lab

    def move_to(self, q_rad, timeout_s=30.0):
        lab = self.lab
        q = np.asarray(q_rad, dtype=np.float64)
        lo, hi = lab.twin.geom.stroke
        if q.shape != (3,) or np.any(~np.isfinite(q)) or np.any((q < lo) | (q > hi)):
            raise InstrumentError(self.name, f"target {q.tolist()} rad outside the stroke "
                                  f"[{lo}, {hi}]", code="STROKE")
        d = lab.s.move_time(q - lab.q)
        lab.schedule.add_move(lab.t, lab.t + d, q - lab.q)
        lab.t += d
        lab.q = q.copy()

    def read_encoders(self, timeout_s=30.0):
        return self.lab.q.copy()


class SimInterferometers(Interferometers):
    def __init__(self, lab):
        self.lab = lab
        self.axes = lab.axes

    def zero(self, timeout_s=30.0):
        truth = self.lab.truth_now(self.lab.t)
        self.lab.zero_path = {a: float(truth.optical_path_m[a][0]) for a in AXES}

    def read(self, timeout_s=30.0):
        lab = self.lab
        t_mid = lab.t + 0.5 * lab.s.window_s
        truth = lab.truth_now(t_mid)
        row = lab.ifm_bank.take(lab.windows, lab.windows + 1)
        lab.windows += 1
        vals, stds = interferometer_values(truth.optical_path_m, truth.n_comp, lab.zero_path,
                                           self.axes, row, lab.s)
        lab.t += lab.s.window_s
        return InterferometerReading(
            t_s=t_mid, displacement_m={a: float(vals[0, i]) for i, a in enumerate(self.axes)},
            std_m={a: float(stds[0, i]) for i, a in enumerate(self.axes)},
            n_samples=lab.s.samples_per_window, window_s=lab.s.window_s)


class SimAutocollimators(Autocollimators):
    channels = AC_CHANNELS

    def __init__(self, lab):
        self.lab = lab

    def read(self, timeout_s=30.0):
        lab = self.lab
        truth = lab.truth_now(lab.t)
        row = lab.ac_bank.take(lab.ac_reads, lab.ac_reads + 1)
        lab.ac_reads += 1
        ang, ok = autocollimator_values(truth, row, lab.s)
        t = lab.t
        lab.t += lab.s.ac_read_s
        return AngleReading(t_s=t, angles_rad={c: float(ang[0, i]) for i, c in enumerate(AC_CHANNELS)},
                            in_range={c: bool(ok[0, i]) for i, c in enumerate(AC_CHANNELS)})


class SimThermometers(ThermometerScanner):
    def __init__(self, lab):
        self.lab = lab
        self.sensors = lab.sensors

    def scan(self, timeout_s=30.0):
        lab = self.lab
        k = int(np.floor(lab.t / lab.s.scan_period_s))
        lab.twin.advance(lab.t, lab.schedule)
        T = scan_temperatures(lab.twin, lab.s, lab.T_bank, self.sensors, np.array([k]))[0]
        return TemperatureScan(t_s=k * lab.s.scan_period_s,
                               temperatures_C={n: float(v) for n, v in zip(self.sensors, T)})


class SimBarometer(Barometer):
    def __init__(self, lab):
        self.lab = lab

    def read(self, timeout_s=30.0):
        return PressureReading(*self.lab.air_record("p_Pa"))


class SimHygrometer(Hygrometer):
    def __init__(self, lab):
        self.lab = lab

    def read(self, timeout_s=30.0):
        return HumidityReading(*self.lab.air_record("RH_pct"))


class SimCoils(CoilSupply):
    def __init__(self, lab):
        self.lab = lab

    def set_currents(self, currents_A, timeout_s=30.0):
        lab = self.lab
        I = np.asarray(currents_A, dtype=np.float64)
        if I.shape != (3,) or not np.all(np.abs(I) <= 2.0 + 1e-12):     # NaN too
            raise InstrumentError(self.name, f"currents {I.tolist()} A outside +-2 A", code="RANGE")
        lab.schedule.set_currents(lab.t, I)
        lab.currents = I.copy()
        lab.t += lab.s.coil_settle_s

    def read_currents(self, timeout_s=30.0):
        return self.lab.currents.copy()
