"""The papers' measurement campaigns: plans, the executor over the instrument interface, and
the twin's vectorised fast path that produces the same data.

A plan is the ordered list of points (session, position, split, motor coordinates, coil
currents, nominal force, readings per point). ``run_campaign`` executes it through any
``InstrumentSet`` (simulated, or serial drivers in hw/): per session it zeroes the
interferometers at home; per point it sets the coil currents, moves, waits, takes the readings
(re-reading a window whose sample std fails the acceptance rule), reads the autocollimators
and the last temperature scan.  ``simulate_campaign`` computes the same timeline with array
operations and evaluates the twin once for all readings.  Both assemble rows with ``_rows``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import pandas as pd

from deltatwin.progress import progress_bar
from deltatwin.twin.instruments.interface import InstrumentError, InstrumentSet
from deltatwin.twin.instruments.optics import (
    AC_CHANNELS,
    AXES,
    COSINE_ANGLES,
    cosine_correction,
    cosine_factor,
)
from deltatwin.twin.instruments.simulated import (
    InstrumentSettings,
    SimulatedLab,
    air_sensor_readings,
    autocollimator_values,
    interferometer_values,
    scan_temperatures,
)
from deltatwin.twin.world import Schedule, Twin


@dataclass(frozen=True)
class Plan:
    sessions: tuple[tuple[str, tuple[str, ...]], ...]   # (name, interferometer axes)
    session: np.ndarray      # (N,) index into sessions, non-decreasing
    pos_id: np.ndarray       # (N,)
    split: np.ndarray        # (N,) "cal" / "val"
    q: np.ndarray            # (N,3) rad
    currents_A: np.ndarray   # (N,3)
    F_N: np.ndarray          # (N,) nominal force
    readings: int            # readings per point

    def __len__(self):
        return self.q.shape[0]


def _stroke_grid(stroke, levels: int, margin: float) -> np.ndarray:
    lo, hi = stroke
    g = np.linspace(lo + margin, hi - margin, levels)
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)


def thermal_plan(rng, stroke, n_positions: int, cal_fraction: float, sessions) -> Plan:
    """First paper: random positions in the stroke cube, 70/30 cal/val by position, visited in
    random order; ``sessions`` = [(name, axes, n_cal_points, n_val_points), ...]."""
    lo, hi = stroke
    q_pos = rng.uniform(lo, hi, (n_positions, 3))
    is_cal = rng.permutation(n_positions) < int(round(cal_fraction * n_positions))
    cal_ids, val_ids = np.flatnonzero(is_cal), np.flatnonzero(~is_cal)
    parts = []
    for k, (_, _, n_cal, n_val) in enumerate(sessions):
        ids = np.concatenate([rng.choice(cal_ids, n_cal), rng.choice(val_ids, n_val)])
        ids = ids[rng.permutation(ids.size)]
        parts.append((np.full(ids.size, k), ids))
    sess = np.concatenate([p[0] for p in parts])
    ids = np.concatenate([p[1] for p in parts])
    n = ids.size
    return Plan(sessions=tuple((s[0], tuple(s[1])) for s in sessions), session=sess, pos_id=ids,
                split=np.where(is_cal[ids], "cal", "val"), q=q_pos[ids], currents_A=np.zeros((n, 3)),
                F_N=np.zeros(n), readings=1)


def force_plan(stroke, cal_levels: int, val_levels: int, forces_N, force_per_A: float,
               readings: int, axes=AXES, interleaved: bool = False) -> Plan:
    """Second paper: a cal grid and a non-coincident val grid of motor coordinates, each
    position at every force (same current in the three coils). The paper measures the whole
    cal grid, then the val grid; ``interleaved`` visits them merged in proportion instead, so
    that validation meets the conditions (temperatures drifting over the campaign) calibration
    saw."""
    lo, hi = stroke
    margin = 0.05 * (hi - lo)
    cal = _stroke_grid(stroke, cal_levels, margin)
    step = (hi - lo - 2 * margin) / (val_levels)
    val = _stroke_grid(stroke, val_levels, margin + 0.5 * step)
    q_pos = np.concatenate([cal, val])
    split = np.array(["cal"] * len(cal) + ["val"] * len(val))
    if interleaved:
        progress = np.concatenate([(np.arange(len(cal)) + 0.5) / len(cal),
                                   (np.arange(len(val)) + 0.5) / len(val)])
        order = np.argsort(progress, kind="stable")
        q_pos, split = q_pos[order], split[order]
    forces = np.asarray(forces_N, dtype=np.float64)
    ids = np.repeat(np.arange(len(q_pos)), forces.size)
    F = np.tile(forces, len(q_pos))
    I = np.repeat((F / force_per_A)[:, None], 3, axis=1)
    return Plan(sessions=(("xyz", tuple(axes)),), session=np.zeros(ids.size, int), pos_id=ids,
                split=split[ids], q=q_pos[ids], currents_A=I, F_N=F, readings=readings)


def _rows(plan: Plan, t_s, ifm, ifm_std, ac, T, sensors, zero_ac, cosine: bool,
          dead_path: dict, air: dict | None = None) -> pd.DataFrame:
    """Dataset rows from per-point arrays: ifm (N, readings, 3 axes; NaN where not measured),
    ac (N, readings, 4), T (N, n_sensors); zero_ac (N,4) the session zero's angles; ``air``
    the barometer's and hygrometer's records ({"p_Pa": (N,), "RH_pct": (N,)}, those the
    laboratory has)."""
    df = pd.DataFrame({"t_s": t_s, "pos_id": plan.pos_id.astype(np.int64), "split": plan.split,
                       "session": np.array([plan.sessions[k][0] for k in plan.session]),
                       "q1_rad": plan.q[:, 0], "q2_rad": plan.q[:, 1], "q3_rad": plan.q[:, 2]})
    ac_mean = np.mean(ac, axis=1)                                   # NaN if any out of range
    for i, c in enumerate(AC_CHANNELS):
        df[f"{c}_arcsec"] = np.degrees(ac_mean[:, i]) * 3600.0
    for k, a in enumerate(AXES):
        x = ifm[:, :, k]
        if np.all(np.isnan(x)):
            continue
        if cosine:
            ia, ib = (AC_CHANNELS.index(c) for c in COSINE_ANGLES[a])
            x = cosine_correction(x, dead_path[a], cosine_factor(ac[:, :, ia], ac[:, :, ib]),
                                  cosine_factor(zero_ac[:, None, ia], zero_ac[:, None, ib]))
        df[f"{a}_nm"] = np.mean(x, axis=1) * 1e9
        df[f"{a}_std_nm"] = np.max(ifm_std[:, :, k], axis=1) * 1e9
        if plan.readings > 1:
            df[f"{a}_repeat_std_nm"] = np.std(x, axis=1, ddof=1) * 1e9
    for j, name in enumerate(sensors):
        df[f"T_{name}_C"] = T[:, j]
    for column, values in (air or {}).items():
        df[column] = values
    for i in range(3):
        df[f"coil{i + 1}_A"] = plan.currents_A[:, i]
    df["F_N"] = plan.F_N
    df["cosine_corrected"] = cosine
    return df


COIL_ZERO_TOLERANCE_A = 1e-3   # ~1 mN of force (2 A ~ 2 N): well below a nanometre
HOME_TOLERANCE_RAD = 1e-5      # encoders at home: the robot went there, not a precision figure
# a zero settle's excursion, every motor: the controllers settle anew on the way back (the
# twin's servo settling draws at every move's end), the moves take ~1 s and heat nothing, and
# home is approached from the same side every time
HOME_EXCURSION_RAD = 0.005


def known_state(inst: InstrumentSet) -> None:
    """Put the instruments in the state a session starts from and check it: the coil currents
    read back, and switched off (then read back again) unless they read 0 A (a supply left at
    1 A by an earlier session would offset every reading; one that reads 0 A is not sent an
    order, which on the simulated coils would be a load change); robot home and its encoders
    read back. Raises ``InstrumentError`` naming the instrument when a read-back disagrees.
    (The interferometers are zeroed and the autocollimators read next, by the caller; the
    thermometer scanner is set up on connecting.)"""
    if inst.coils is not None:
        read = np.asarray(inst.coils.read_currents(), dtype=np.float64)
        if not np.all(np.abs(read) <= COIL_ZERO_TOLERANCE_A):
            inst.coils.set_currents(np.zeros(3))
            read = np.asarray(inst.coils.read_currents(), dtype=np.float64)
        if not np.all(np.abs(read) <= COIL_ZERO_TOLERANCE_A):
            raise InstrumentError(inst.coils.name, f"set to 0 A at the session start but reads "
                                  f"back {read.tolist()} A (tolerance "
                                  f"{COIL_ZERO_TOLERANCE_A * 1e3:g} mA)")
    inst.robot.move_to(np.zeros(3))
    q = np.asarray(inst.robot.read_encoders(), dtype=np.float64)
    if not np.all(np.abs(q) <= HOME_TOLERANCE_RAD):
        raise InstrumentError(inst.robot.name, f"sent home at the session start but its "
                              f"encoders read {q.tolist()} rad (tolerance "
                              f"{HOME_TOLERANCE_RAD:g} rad)")


def accepted_reading(inst: InstrumentSet, settings: InstrumentSettings, axes, what: str,
                     r: int):
    """Reading ``r`` of ``what`` (a point, a zero settle): one interferometer window that
    passes the acceptance rule on ``axes`` (sample std below ``std_limit_m``), re-reading up to
    ``max_rereads`` times."""
    import logging

    for _attempt in range(settings.max_rereads + 1):
        reading = inst.interferometers.read()
        if all(reading.std_m[a] < settings.std_limit_m for a in axes):
            return reading
        logging.getLogger(__name__).info(
            "%s reading %d: window rejected (sample std %s nm, limit %.0f nm); taking it again",
            what, r, {a: round(reading.std_m[a] * 1e9, 1) for a in axes},
            settings.std_limit_m * 1e9)
    raise InstrumentError(inst.interferometers.name,
                          f"{what}: sample std above {settings.std_limit_m * 1e9:.0f}"
                          f" nm in {settings.max_rereads + 1} windows in a row")


def zero_offset(inst: InstrumentSet, settings: InstrumentSettings, axes, readings: int,
                settles: int, zero_t_s: float) -> tuple[np.ndarray, float]:
    """The zero as the mean of ``settles`` home settles: (offset (m per axis of ``AXES``, NaN
    off ``axes``), the time it refers to (s)). The offset is to be subtracted from every
    reading counted from the interferometers' zero just set at home at ``zero_t_s`` (the first
    settle, reading 0 by definition): ``settles - 1`` times the robot moves
    ``HOME_EXCURSION_RAD`` away and back home, waits, and takes ``readings`` accepted windows.
    With servo settling the zero otherwise holds one settle's error for the whole session; the
    mean of n holds 1/sqrt(n) of it. It refers to the settles' mean time: the robot drifts
    meanwhile (paper-thermal's home, up to 15 nm along X in 35 s), and a model is to be given
    the conditions of that time."""
    total, times = np.zeros(len(AXES)), [zero_t_s]
    for i in range(1, settles):
        inst.robot.move_to(np.full(3, HOME_EXCURSION_RAD))
        inst.robot.move_to(np.zeros(3))
        inst.clock.sleep(settings.wait_s)
        t = 0.0
        for r in range(readings):
            reading = accepted_reading(inst, settings, axes, f"zero settle {i + 1}", r)
            total += [reading.displacement_m.get(a, np.nan) for a in AXES]
            t += reading.t_s / readings
        times.append(t)
    offset = np.where([a in axes for a in AXES], total / (settles * readings), np.nan)
    return offset, float(np.mean(times))


def run_campaign(plan: Plan, inst: InstrumentSet, settings: InstrumentSettings, cosine: bool,
                 dead_path: dict, progress: bool = True, journal=None,
                 replay: bool = False, controller=None, zero_settles: int = 1) -> pd.DataFrame:
    """Execute ``plan`` through the instrument interface, point by point.

    ``journal`` (a ``twin.journal.Journal``, optional): each accepted point's raw readings are
    appended (and fsync'ed) before the next move; points already in it are not taken again
    (resume) and the dataset is assembled from it. A resume re-establishes the instruments as a
    session start does (coils off, home, wait, zero the interferometers, autocollimator zero
    reading): the zero did not survive the crash, so the resumed points are relative to this
    new zero (each journaled point carries the time and the autocollimator angles of the zero it
    refers to, ``zero_t_s`` and ``zero_ac_rad``). Before that, the clock is let run on to the
    end of the last journaled point (the time it would have reached) if it is behind: a rebuilt
    simulated or emulated world starts again at 0 s.

    ``replay``: the instruments are a simulated world rebuilt after a crash (nothing of it
    survived): the journaled points are taken again, with the zeros of earlier resumes where they
    were, to bring that world (clock, heat, noise streams) to where it was, and each must give
    exactly the journaled values (else ``JournalError``); then the campaign resumes as above.

    ``controller`` (optional; compensation in the loop): decides each point's motor coordinates
    from what the instruments read at that moment, in place of ``plan.q``. At every zero the
    temperature scan is recorded with it (``zero_T_C``); per point, after the coil currents
    are set and before the move, ``controller.command(k, inst, zero)`` returns ``(q (3,) rad,
    record)`` (it may let the clock run, e.g. to fill its temperature history). The commanded
    q (``q_cmd_rad``) and the record (``control``: what it read and decided) are journaled
    with the point and give the dataset's motor coordinates. On a resume the journaled points
    are handed to ``controller.replayed(k, point)`` in order, so that its state (the temperature
    history) is what it was; in a replay it decides them again, and must decide the same.

    ``zero_settles`` (n): every zero is the mean of n home settles (``zero_offset``; its
    offsets, ``zero_offset_m``, are journaled with each point and subtracted from its
    readings; ``zero_t_s`` is then the settles' mean time, ``zero_scan_t_s`` the time the
    interferometers were zeroed and the zero's scan read); 1, the papers' zero: the readings
    set to 0 at home once.
    """
    import json
    import logging

    from deltatwin.twin.journal import JournalError, canonical_json

    log = logging.getLogger(__name__)
    n, R = len(plan), plan.readings
    if isinstance(zero_settles, bool) or not isinstance(zero_settles, int) or zero_settles < 1:
        raise ValueError(f"zero_settles must be an integer >= 1, got {zero_settles!r}")
    sensors = inst.thermometers.sensors
    offset = np.zeros(len(AXES))
    done = {} if journal is None else journal.points()
    if sorted(done) != list(range(len(done))) or len(done) > n:
        raise JournalError(f"{journal.path}: holds points {sorted(done)[:5]}... of a plan of {n}:"
                           " not the prefix this campaign writes")
    resume_at = len(done) if 0 < len(done) < n else None
    replay = replay and resume_at is not None     # a complete journal needs no world
    if resume_at is not None:
        log.info("resuming at point %d of %d (%d journaled)%s", resume_at, n, len(done),
                 ", replaying the journaled points first" if replay else "")
    currents = np.zeros(3)
    zero = None
    bar = progress_bar(total=n, initial=len(done), desc="campaign", unit="pt", disable=not progress)
    for k in range(n):
        if k in done and not replay:
            if controller is not None:
                controller.replayed(k, done[k])
            continue
        session = plan.session[k]
        new_session = k == 0 or session != plan.session[k - 1]
        rezero = k == resume_at or (k in done and done[k]["rezero"])
        if rezero:                                # the clock runs on from the last point
            behind = done[k - 1]["t_s"] + settings.overhead_s - inst.clock.now()
            if behind > 0:
                inst.clock.sleep(behind)
        if new_session or rezero:
            if new_session and k > 0:
                inst.clock.sleep(settings.session_gap_s)
            known_state(inst)
            currents = np.zeros(3)
            inst.clock.sleep(settings.wait_s)
            zero_t = inst.clock.now()
            inst.interferometers.zero()
            ac0 = inst.autocollimators.read()
            zero = {"zero_t_s": zero_t, "zero_ac_rad": [ac0.angles_rad[c] for c in AC_CHANNELS]}
            if controller is not None:          # the conditions the zero was taken in
                scan0 = inst.thermometers.scan()
                zero["zero_T_C"] = [scan0.temperatures_C[s] for s in sensors]
            if zero_settles > 1:                # the zero then refers to the settles' mean time
                offset, zero["zero_t_s"] = zero_offset(inst, settings, plan.sessions[session][1],
                                                       R, zero_settles, zero_t)
                zero.update(zero_offset_m=offset, zero_scan_t_s=zero_t)
            if rezero and not new_session:
                log.warning("point %d: interferometers zeroed again at home at t = %.1f s (the "
                            "zero of session %r did not survive the interruption)", k, zero_t,
                            plan.sessions[session][0])
        if np.any(plan.currents_A[k] != currents):
            inst.coils.set_currents(plan.currents_A[k])
            currents = plan.currents_A[k].copy()
        q_k, control = plan.q[k], None
        if controller is not None:                # a replayed point decides again: compared
            q_k, control = controller.command(k, inst, zero)
            q_k = np.asarray(q_k, dtype=np.float64)
        inst.robot.move_to(q_k)
        inst.clock.sleep(settings.wait_s)
        axes = plan.sessions[session][1]
        ifm = np.full((R, 3), np.nan)
        ifm_std = np.full((R, 3), np.nan)
        ac = np.full((R, 4), np.nan)
        for r in range(R):
            reading = accepted_reading(inst, settings, axes, f"point {k}", r)
            for a in axes:
                ifm[r, AXES.index(a)] = reading.displacement_m[a] - offset[AXES.index(a)]
                ifm_std[r, AXES.index(a)] = reading.std_m[a]
            ang = inst.autocollimators.read()
            ac[r] = [ang.angles_rad[c] for c in AC_CHANNELS]
        t_end = inst.clock.now()
        scan = inst.thermometers.scan()
        point = {"pos_id": int(plan.pos_id[k]), "t_s": t_end, **zero, "rezero": bool(rezero),
                 "ifm_m": ifm, "ifm_std_m": ifm_std, "ac_rad": ac,
                 "T_C": [scan.temperatures_C[s] for s in sensors]}
        if inst.barometer is not None:
            point["p_Pa"] = inst.barometer.read().pressure_Pa
        if inst.hygrometer is not None:
            point["RH_pct"] = inst.hygrometer.read().humidity_pct
        if controller is not None:
            point.update(q_cmd_rad=q_k, control=control)
        if k in done:                             # replay: the rebuilt world must agree
            if canonical_json(point) != canonical_json(done[k]):
                raise JournalError(f"{journal.path}: point {k} taken again in the rebuilt "
                                   "simulated world differs from the journal (another deltatwin "
                                   "version or scenario file?); cannot resume it")
        else:
            if journal is not None:
                journal.append(k, point)
            done[k] = json.loads(canonical_json(point))
            bar.update()
        inst.clock.sleep(settings.overhead_s)
    bar.close()
    pts = [done[k] for k in range(n)]
    arr = lambda key: np.array([p[key] for p in pts], dtype=np.float64)
    if controller is not None:
        plan = dataclasses.replace(plan, q=arr("q_cmd_rad"))
    air = {c: arr(c) for c in ("p_Pa", "RH_pct") if all(c in p for p in pts)}
    return _rows(plan, arr("t_s"), arr("ifm_m"), arr("ifm_std_m"), arr("ac_rad"), arr("T_C"),
                 sensors, arr("zero_ac_rad"), cosine, dead_path, air)


def simulate_campaign(plan: Plan, twin: Twin, settings: InstrumentSettings, cosine: bool,
                      dead_path: dict, noise_free: bool = False):
    """The same campaign as ``run_campaign`` over the simulated instruments, vectorised.
    With ``noise_free`` also the dataset a perfect instrument would have given on the same
    timeline (no noise, no quantisation, exact angles; motors at their commanded angles):
    ``(df, df_noise_free)``. The difference is what no model can predict, from which the
    dataset's noise floor follows."""
    s = settings
    lab = SimulatedLab(twin, s)                 # for its noise banks (same streams, same layout)
    n, R = len(plan), plan.readings
    schedule = Schedule()
    t, q_prev, I_prev, windows, ac_reads = 0.0, np.zeros(3), np.zeros(3), 0, 0
    t_mid = np.zeros((n, R))
    t_ac = np.zeros((n, R))
    t_s = np.zeros(n)
    win_rows = np.zeros((n, R), int)
    ac_rows = np.zeros((n, R), int)
    zero_events = []                            # (t, session index, ac row, point slice)
    for k_sess in range(len(plan.sessions)):
        idx = np.flatnonzero(plan.session == k_sess)
        if idx.size == 0:
            continue
        if k_sess > 0:
            t += s.session_gap_s
        if np.any(I_prev != 0):
            schedule.set_currents(t, np.zeros(3))
            I_prev = np.zeros(3)
            t += s.coil_settle_s
        d = s.move_time(-q_prev)
        schedule.add_move(t, t + d, -q_prev)
        t += d + s.wait_s
        q_prev = np.zeros(3)
        zero_events.append((t, k_sess, ac_reads, idx))
        ac_reads += 1
        t += s.ac_read_s
        # this session's points
        q = plan.q[idx]
        I = plan.currents_A[idx]
        changed = np.any(I != np.vstack([I_prev, I[:-1]]), axis=1)
        dq = q - np.vstack([q_prev, q[:-1]])
        move = s.move_base_s + np.max(np.abs(dq), axis=1) / s.speed_rad_s
        # accepted windows: this session's axes decide
        axes = [AXES.index(a) for a in plan.sessions[k_sess][1]]
        need = idx.size * R
        stop = windows + need
        # at most max_rereads + 1 windows per reading: beyond, some reading has failed anyway
        limit = windows + need * (s.max_rereads + 1)
        while True:
            rows = lab.ifm_bank.take(windows, stop)
            ok = np.all(rows[:, 1, axes] < s.std_limit_m, axis=1)
            acc = np.flatnonzero(ok)
            if acc.size >= need or stop >= limit:
                break
            stop = min(stop + need // 10 + 16, limit)
        acc = acc[:need] + windows
        attempts = np.diff(np.concatenate([[windows - 1], acc]))
        if acc.size < need:     # the next reading found no window up to the limit: the windows
            # it tried exceed max_rereads + 1 (they sum past need * (max_rereads + 1))
            attempts = np.append(attempts, stop - (acc[-1] if acc.size else windows - 1))
        if attempts.max() > s.max_rereads + 1:
            bad = int(np.argmax(attempts > s.max_rereads + 1)) // R
            raise InstrumentError("interferometers", f"point {int(idx[bad])}: sample std above "
                                  f"{s.std_limit_m * 1e9:.0f} nm in {s.max_rereads + 1} windows in a row")
        windows = int(acc[-1]) + 1
        reading_dur = (attempts * s.window_s + s.ac_read_s).reshape(-1, R)
        lead = changed * s.coil_settle_s + move + s.wait_s           # before the first reading
        dur = lead + reading_dur.sum(axis=1) + s.overhead_s
        start = t + np.concatenate([[0.0], np.cumsum(dur)[:-1]])
        first = start + lead
        before = np.concatenate([np.zeros((idx.size, 1)), np.cumsum(reading_dur, axis=1)[:, :-1]],
                                axis=1)
        att = attempts.reshape(-1, R)
        t_ac[idx] = first[:, None] + before + att * s.window_s
        t_mid[idx] = t_ac[idx] - 0.5 * s.window_s
        t_s[idx] = first + reading_dur.sum(axis=1)
        win_rows[idx] = acc.reshape(-1, R)
        ac_rows[idx] = ac_reads + np.arange(idx.size * R).reshape(-1, R)
        ac_reads += idx.size * R
        for j in np.flatnonzero(changed):
            schedule.set_currents(start[j], I[j])
        move_start = start + changed * s.coil_settle_s
        schedule.moves.extend((float(a), float(a + m), v / np.abs(v).max()
                               if np.abs(v).max() > 0 else np.abs(v))
                              for a, m, v in zip(move_start, move, dq))
        t = float(start[-1] + dur[-1])
        q_prev, I_prev = q[-1].copy(), I[-1].copy()
    twin.advance(t, schedule)
    # zeros: truth at home with the currents then in force (zero)
    zero_ac = np.zeros((n, 4))
    zero_ac_exact = np.zeros((n, 4))
    zero_path, zero_path_still = {}, {}
    for tz, k_sess, ac_row, idx in zero_events:
        truth = twin.truth(twin.points([tz], np.zeros((1, 3)), np.zeros((1, 3))))
        zero_path[k_sess] = {a: float(truth.optical_path_m[a][0]) for a in AXES}
        if noise_free and twin.settling is not None:
            still = twin.truth(twin.points([tz], np.zeros((1, 3)), np.zeros((1, 3)), settled=False))
            zero_path_still[k_sess] = {a: float(still.optical_path_m[a][0]) for a in AXES}
        ang, _ = autocollimator_values(truth, lab.ac_bank.take(ac_row, ac_row + 1), s)
        zero_ac[idx] = ang[0]
        zero_ac_exact[idx] = [truth.angles_rad[c][0] for c in AC_CHANNELS]
    qr = np.repeat(plan.q, R, axis=0)
    Ir = np.repeat(plan.currents_A, R, axis=0)
    truth_mid = twin.truth(twin.points(t_mid.reshape(-1), qr, Ir))
    truth_ac = twin.truth(twin.points(t_ac.reshape(-1), qr, Ir))
    sess_r = np.repeat(plan.session, R)
    noise = lab.ifm_bank.take(0, windows)[win_rows.reshape(-1)]
    ac_noise = lab.ac_bank.take(0, ac_reads)[ac_rows.reshape(-1)]
    scan_k = np.floor(t_s / s.scan_period_s).astype(int)
    T = scan_temperatures(twin, s, lab.T_bank, lab.sensors, scan_k)
    air = air_sensor_readings(twin, s, lab.air_bank, scan_k)

    def dataset(noise, ac_noise, zero_ac, s, truth_mid=truth_mid, zero_path=zero_path):
        ifm = np.full((n, R, 3), np.nan)
        ifm_std = np.full((n, R, 3), np.nan)
        flat, flat_std = ifm.reshape(-1, 3), ifm_std.reshape(-1, 3)   # views: rows = readings
        for k_sess, (_, axes) in enumerate(plan.sessions):
            m = np.flatnonzero(sess_r == k_sess)
            if m.size == 0:
                continue
            vals, stds = interferometer_values(
                {a: v[m] for a, v in truth_mid.optical_path_m.items()},
                {a: v[m] for a, v in truth_mid.n_comp.items()}, zero_path[k_sess], axes,
                noise[m], s)
            cols = [AXES.index(a) for a in axes]
            flat[np.ix_(m, cols)] = vals
            flat_std[np.ix_(m, cols)] = stds
        ang, _ = autocollimator_values(truth_ac, ac_noise, s)
        return _rows(plan, t_s, ifm, ifm_std, ang.reshape(n, R, 4), T, lab.sensors, zero_ac,
                     cosine, dead_path, air)

    df = dataset(noise, ac_noise, zero_ac, s)
    if not noise_free:
        return df
    perfect = dataclasses.replace(s, resolution_m=0.0, ac_resolution_rad=0.0,
                                  ac_range_rad=np.inf)
    if twin.settling is None:
        clean = dataset(np.zeros_like(noise), np.zeros_like(ac_noise), zero_ac_exact, perfect)
    else:
        # the true model cannot know where the controllers settled: the noise floor counts it
        still = twin.truth(twin.points(t_mid.reshape(-1), qr, Ir, settled=False))
        clean = dataset(np.zeros_like(noise), np.zeros_like(ac_noise), zero_ac_exact, perfect,
                        still, zero_path_still)
    return df, clean
