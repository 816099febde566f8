"""``deltatwin effect new NAME``: write the researcher's own effect as a documented skeleton
(docs/effects.md), optionally seeded from the missing term's form a diagnosis proposed
(``deltatwin diagnose DATA --model M --json > diagnosis.json``; ``--from diagnosis.json``)."""
from __future__ import annotations

import json
import keyword
import math
import textwrap
from pathlib import Path

from deltatwin.files import atomic_write_text

# how a proposed term's variable is read at the optics stage (points: twin/world.py Points)
AT_OPTICS = {"q1_rad": "points.q[:, 0]", "q2_rad": "points.q[:, 1]", "q3_rad": "points.q[:, 2]",
             "t_s": "points.t_s", "x_m": "points.pose.p[:, 0]", "y_m": "points.pose.p[:, 1]",
             "z_m": "points.pose.p[:, 2]", "dir_q1": "points.move_direction[:, 0]",
             "dir_q2": "points.move_direction[:, 1]", "dir_q3": "points.move_direction[:, 2]",
             "coil1_A": "points.currents_A[:, 0]", "coil2_A": "points.currents_A[:, 1]",
             "coil3_A": "points.currents_A[:, 2]",
             # the campaign's nominal force: force_per_A (scenario [campaign], 1 N/A in the
             # shipped ones) times the coils' mean current
             "F_N": "FORCE_PER_A * np.mean(points.currents_A, axis=1)"}
UNITS = {"q": "rad", "t": "s", "x": "m", "y": "m", "z": "m", "d": "-", "c": "A", "F": "N"}

HEADER = '''"""{name}: {summary}

Your own effect for deltatwin (docs/effects.md). Use it like a library effect:

    deltatwin fit DATA --effects {baseline}./{file}:{cls} -o fitted.toml
    deltatwin diagnose DATA --model fitted.toml
    # in a scenario: [effects] on = [..., "./{file}:{cls}"], parameters in [effects.{name}]

Units are SI (m, rad, s, N, K). Parameters with a ``fit_scale`` are what a fit adjusts
(``fit_scale``: their typical size); the others are constants you know.
{origin}"""
import numpy as np

from deltatwin.twin.effects import Effect, Parameter, shift_reading
{constants}

class {cls}(Effect):
    name = "{name}"
    summary = "{summary}"
    parameters = (
{parameters}
    )
{methods}'''


OPTICS = '''
    def optics(self, points, optics):
        """Stage 'optics': change what the interferometers read. ``points`` holds the
        conditions of N readings (t_s (N,) s, q (N,3) rad, currents_A (N,3), move_direction
        (N,3) sign of each motor's last move, pose.p (N,3) m the platform's position);
        ``shift_reading(optics, axis, d_m)`` adds d_m (N,) m to the reading of an axis."""
{body}
'''

WRENCH = '''
    def wrench(self, points):
        """Stage 'wrench': the load on the platform, (N,6): force (N) and moment (N*m) about
        the platform origin, world frame; the model's statics turn it into a deflection."""
        current = np.mean(points.currents_A, axis=1)     # A, the coils' mean current
        w = np.zeros((current.shape[0], 6))
{body}
        return w
'''

MOTOR_ANGLES = '''
    def motor_angles(self, points):
        """Stage 'motor_angles': where the motors sit off their encoders' readings, (N,3) rad
        (points.q (N,3) rad the encoders' readings, points.move_direction (N,3) the sign of
        each motor's last move); the model's kinematics carry it to every reading."""
        d = np.zeros_like(points.q)
{body}
        return d
'''
# a periodic error's period is fitted too, its typical size this fraction of the scanned one:
# the periodogram's grid (3 frequencies per 1 / range) leaves it ~0.1-1 % off, which over the
# tens of periods a motor's range holds shifts the phase by a good part of a period (seed 606
# g10: 3.383 against 3.388 mrad, 13.7 nm held at the scan against 12.2 with the injected
# effect; 12.4 refined)
PERIOD_REFINED = 1e-3
# the kinds of the proposed terms written at another stage than the optics: a load's (wrench),
# a motor's (motor_angles), each once whatever axes it was listed on
STAGED = ("load", "motor_sign", "motor_sine")


def camel(name: str) -> str:
    return "".join(p.capitalize() for p in name.split("_"))


def _num(x: float) -> str:
    return repr(float(f"{x:.6g}"))


def _term_code(axis: str, term: dict, k: int) -> tuple[list[str], str, str | None]:
    """(parameter lines, expression in m, or None and a note) of one proposed term."""
    var = term["variable"]
    v = AT_OPTICS.get(var)
    tag = f"{axis}{k}"
    if v is None:
        return [], "", "\n".join(textwrap.wrap(
            f"{term['formula']}: {var} is not known at the optics stage; read it from the "
            "stage that has it (docs/effects.md)", 92, initial_indent="        # ",
            subsequent_indent="        # "))
    kind = term["kind"]
    unit = UNITS.get(var[0], "-")
    if kind == "sine":
        phase, amp = term["phase_rad"], term["amplitude_nm"] * 1e-9
        a, b = amp * math.cos(phase), amp * math.sin(phase)
        params = [f'Parameter("{tag}_sin_m", "m", {_num(a)}, "{axis}: sine amplitude in {var}", '
                  f"fit_scale={_num(max(amp, 1e-9))}),",
                  f'Parameter("{tag}_cos_m", "m", {_num(b)}, "{axis}: cosine amplitude in {var}", '
                  f"fit_scale={_num(max(amp, 1e-9))}),",
                  f'Parameter("{tag}_period", "{unit}", {_num(term["period"])}, '
                  f'"{axis}: period in {var}"),']
        expr = (f"self.{tag}_sin_m * np.sin(2 * np.pi * {v} / self.{tag}_period) + "
                f"self.{tag}_cos_m * np.cos(2 * np.pi * {v} / self.{tag}_period)")
    elif kind in ("step", "ramp"):
        size = term["coefficient_nm"] * 1e-9 if kind == "step" else \
            term["coefficient_nm_per_h"] * 1e-9 / 3600.0
        unit_c = "m" if kind == "step" else "m/s"
        params = [f'Parameter("{tag}_{kind}_{unit_c.replace("/", "_per_")}", "{unit_c}", '
                  f'{_num(size)}, "{axis}: {kind} size", fit_scale={_num(max(abs(size), 1e-12))}),',
                  f'Parameter("{tag}_moment_s", "s", {_num(term["moment_s"])}, '
                  f'"{axis}: when the {kind} starts"),']
        p = f"self.{tag}_{kind}_{unit_c.replace('/', '_per_')}"
        expr = (f"{p} * ({v} > self.{tag}_moment_s)" if kind == "step"
                else f"{p} * np.maximum({v} - self.{tag}_moment_s, 0.0)")
    elif kind == "product":
        power, by, centre, c_si = term["power"], term["by"], term["centre"], term["coefficient_si"]
        params = [f'Parameter("{tag}_m", "m/N^{power}/m", {_num(c_si)}, "{axis}: coefficient of '
                  f'F^{power} ({by} - centre)", fit_scale={_num(max(abs(c_si), 1e-30))}),',
                  f'Parameter("{tag}_centre", "m", {_num(centre)}, "{axis}: centre of {by}"),']
        expr = f"self.{tag}_m * {v} ** {power} * ({AT_OPTICS[by]} - self.{tag}_centre)"
    elif kind == "sign":
        c = term["coefficient_nm"] * 1e-9
        params = [f'Parameter("{tag}_m", "m", {_num(c)}, "{axis}: offset along the last move of '
                  f'{var[4:]}", fit_scale={_num(max(abs(c), 1e-9))}),']
        expr = f"self.{tag}_m * {v}"
    else:
        power, centre, c_si = term["power"], term["centre"], term["coefficient_si"]
        params = [f'Parameter("{tag}_m", "m/{unit}^{power}", {_num(c_si)}, "{axis}: coefficient '
                  f'of ({var} - centre)^{power}", fit_scale={_num(max(abs(c_si), 1e-30))}),',
                  f'Parameter("{tag}_centre", "{unit}", {_num(centre)}, "{axis}: centre"),']
        expr = f"self.{tag}_m * ({v} - self.{tag}_centre) ** {power}"
    return params, expr, None


def _first_of_each(terms: list[dict], keys: tuple[str, ...]) -> list[dict]:
    """The first (strongest) of the proposed terms per value of ``keys``: a term seen on several
    reading axes is written once."""
    first = {}
    for t in terms:
        first.setdefault(tuple(t[k] for k in keys), t)
    return list(first.values())


def _proposed(term: dict) -> list[str]:
    """The proposed term's formula as comment lines of a hook's body."""
    return textwrap.wrap(f"proposed: {term['formula']}", 92, initial_indent="        # ",
                         subsequent_indent="        # ")


def _load_code(terms: list[dict]) -> tuple[list[str], list[str]]:
    """(parameter lines, wrench body lines) of the proposed load terms (model_form.py): one
    force parameter per direction and power of the current, whichever axes it was seen on (the
    first, strongest, gives its starting value)."""
    params, body = [], []
    for t in _first_of_each(terms, ("direction", "power")):
        tag = f"f{t['direction']}{t['power']}_N"
        size = max(abs(t["force_N"]), 1e-3)
        params.append(f'Parameter("{tag}", "N", {_num(t["force_N"])}, "force along '
                      f'{t["direction"]} per (I / 1 A)^{t["power"]}", fit_scale={_num(size)}),')
        body += _proposed(t)
        body.append(f"        w[:, {'xyz'.index(t['direction'])}] += self.{tag} * current"
                    + (f" ** {t['power']}" if t["power"] > 1 else ""))
    return params, body


def _motor_code(terms: list[dict]) -> tuple[list[str], list[str]]:
    """(parameter lines, motor_angles body lines) of the proposed motor terms (model_form.py):
    per motor, its offset along its last move (rad) and its periodic error (sine and cosine
    amplitudes, rad; its period refined from the scanned one: PERIOD_REFINED), once whichever
    axes it was listed on. The amplitudes' typical size (``fit_scale``) is a motor angle
    error's, as the diagnosis' probe declares it, not the seed's: a seed of several urad (a
    backlash on the paper-force grid) as its typical size left the 20-evaluation fit of seeds
    8080 g01 and 777 g04 at 41.8 and 41.5 nm, with the probe's 38.8 and 37.5 (the injected
    effect: 37.3, 37.5)."""
    if not terms:
        return [], []           # the diagnosis' stack (~0.9 s of imports) only where needed
    from deltatwin.calibration.diagnosis.model_form import MotorError

    size = {p.name: p.fit_scale for p in MotorError.parameters}
    params, body = [], []
    for t in _first_of_each(terms, ("kind", "motor")):
        m = t["motor"]
        body += _proposed(t)
        if t["kind"] == "motor_sign":
            params.append(f'Parameter("q{m}_backlash_rad", "rad", {_num(t["backlash_rad"])}, '
                          f'"motor {m} sits this far along its last move", '
                          f"fit_scale={_num(size['backlash_rad'])}),")
            body.append(f"        d[:, {m - 1}] += self.q{m}_backlash_rad * "
                        f"points.move_direction[:, {m - 1}]")
        else:
            params += [f'Parameter("q{m}_sin_rad", "rad", {_num(t["sin_rad"])}, "motor {m}: '
                       f'sine amplitude of its periodic error", '
                       f"fit_scale={_num(size['sin_rad'])}),",
                       f'Parameter("q{m}_cos_rad", "rad", {_num(t["cos_rad"])}, "motor {m}: '
                       f'cosine amplitude of its periodic error", '
                       f"fit_scale={_num(size['cos_rad'])}),",
                       f'Parameter("q{m}_period_rad", "rad", {_num(t["period"])}, '
                       f'"motor {m}: period of its error in q{m}", '
                       f"fit_scale={_num(PERIOD_REFINED * t['period'])}),"]
            phase = f"2 * np.pi * points.q[:, {m - 1}] / self.q{m}_period_rad"
            body += [f"        d[:, {m - 1}] += (self.q{m}_sin_rad * np.sin({phase})",
                     f"                      + self.q{m}_cos_rad * np.cos({phase}))"]
    return params, body


def skeleton(name: str, diagnosis: dict | None = None, source: str = "") -> str:
    """The Python source of the effect ``name``: from the proposed form of ``diagnosis`` (its
    ``unexplained.form``: reading terms at the optics stage, loads at the wrench stage, where a
    motor sits at the motor_angles stage), or a minimal working example (a constant X
    offset)."""
    form = ((diagnosis or {}).get("unexplained") or {}).get("form") or []
    cls = camel(name)
    params, body, uses_force = [], [], False
    loads = [t for f in form for t in f["terms"] if t["kind"] == "load"]
    motors = [t for f in form for t in f["terms"] if t["kind"] in ("motor_sign", "motor_sine")]
    for f in form:
        exprs = []
        for k, term in enumerate(t for t in f["terms"] if t["kind"] not in STAGED):
            p, expr, note = _term_code(f["axis"], term, k)
            if note:
                body.append(note)
                continue
            params += p
            exprs.append(expr)
            uses_force |= "FORCE_PER_A" in expr
        if exprs:
            said = (f"proposed: {'; '.join(t['formula'] for t in f['terms'] if t['kind'] not in STAGED)}"
                    f" (explains {100 * f['explained_fraction']:.0f} % of the validation residual)")
            body += textwrap.wrap(said, 92, initial_indent="        # ",
                                  subsequent_indent="        # ")
            summands = [x for e in exprs for x in e.split(" + ")]
            body.append(f'        shift_reading(optics, "{f["axis"]}", (')
            body += [f"            {'+ ' if i else ''}{x}" for i, x in enumerate(summands)]
            body[-1] += "))"
    if not form:
        params = ['Parameter("offset_m", "m", 0.0, "a constant offset of the X reading", '
                  "fit_scale=10e-9),"]
        body = ["        # replace with your effect; other stages: robot, motor_angles, wrench,",
                "        # part_temperatures, sensed_parts (docs/effects.md)",
                '        shift_reading(optics, "x", np.full(points.t_s.shape, self.offset_m))']
        summary, origin = "describe what it does", ""
    else:
        summary = "the missing term the diagnosis proposed"
        origin = f"\nSeeded from the form the diagnosis proposed ({source}).\n"
    baseline = "".join(f"{e}," for e in (diagnosis or {}).get("effects", []))
    load_params, load_body = _load_code(loads)
    motor_params, motor_body = _motor_code(motors)
    methods = (OPTICS.format(body="\n".join(body)) if body else "") + (
        WRENCH.format(body="\n".join(load_body)) if load_body else "") + (
        MOTOR_ANGLES.format(body="\n".join(motor_body)) if motor_body else "")
    return HEADER.format(
        name=name, cls=cls, file=f"{name}.py", summary=summary, origin=origin,
        baseline=baseline,
        constants="\nFORCE_PER_A = 1.0   # N/A: the campaign's force_per_A\n" if uses_force else "",
        parameters="\n".join(f"        {p}" for p in params + load_params + motor_params),
        methods=methods)


def run_new(args) -> int:
    name = args.name
    if not name.isidentifier() or keyword.iskeyword(name) or name != name.lower():
        raise ValueError(f"effect new {name!r}: the name must be a lower-case identifier "
                         "(letters, digits, _), e.g. periodic_encoder")
    from deltatwin.twin.effects import LIBRARY

    if name in LIBRARY:
        raise ValueError(f"effect new {name!r}: a library effect has that name; choose another")
    diagnosis = None
    if args.from_diagnosis:
        try:
            diagnosis = json.loads(Path(args.from_diagnosis).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"--from {args.from_diagnosis}: not a diagnosis JSON file "
                             f"(`deltatwin diagnose DATA --model M --json`): {exc}") from exc
        if not isinstance(diagnosis, dict) or "unexplained" not in diagnosis:
            raise ValueError(f"--from {args.from_diagnosis}: no 'unexplained' key: not the JSON "
                             "of `deltatwin diagnose --json`")
        if not diagnosis["unexplained"].get("form"):
            raise ValueError(f"--from {args.from_diagnosis}: the diagnosis proposes no form "
                             "(a library effect was claimed, or the residual is noise-like)")
    out = Path(args.output or f"{name}.py")
    if out.exists() and not args.force:
        raise ValueError(f"{out} exists; use --force to overwrite it")
    atomic_write_text(out, skeleton(name, diagnosis, str(args.from_diagnosis or "")))
    print(f"wrote {out}: class {camel(name)} (effect {name!r}); use it with "
          f"--effects ...,{out}:{camel(name)}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("effect", help="write your own effect (docs/effects.md)",
                       description="The researcher's own physical effects (docs/effects.md): use "
                                   "them with --effects ...,./FILE.py:Class or in a scenario.")
    s = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    n = s.add_parser("new", help="write a documented effect skeleton NAME.py",
                     description="Write NAME.py: an Effect subclass, documented, that works as it "
                                 "is (a constant X offset to replace) or, with --from, holds the "
                                 "missing term's form a diagnosis proposed, its coefficients as "
                                 "free parameters.")
    n.add_argument("name", help="the effect's name, a lower-case identifier (periodic_encoder)")
    n.add_argument("--from", dest="from_diagnosis", metavar="DIAGNOSIS_JSON",
                   help="seed it from the missing term's form a diagnosis proposed "
                        "(`deltatwin diagnose DATA --model M --json > diagnosis.json`)")
    n.add_argument("-o", "--output", help="where to write it (default NAME.py)")
    n.add_argument("--force", action="store_true", help="overwrite an existing file")
    n.set_defaults(func=run_new)
