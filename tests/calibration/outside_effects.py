"""Effects outside the library, written as a researcher would (docs/effects.md), injected into
simulated data to test that the diagnosis names what they depend on and proposes their form
(tests/calibration/test_outside_library.py, benchmarks/outside_library.py)."""
import numpy as np

from deltatwin.twin.effects import Effect, Parameter, shift_reading


class PeriodicEncoder(Effect):
    """Motor 1's encoder has a periodic error (a scale grating's interpolation): the motor sits
    at q1 + a sin(2 pi q1 / P) + b cos(2 pi q1 / P)."""
    name = "periodic_encoder"
    summary = "periodic error of encoder 1 with the grating period"
    parameters = (
        Parameter("sin_rad", "rad", 0.0, "sine amplitude", fit_scale=1e-6),
        Parameter("cos_rad", "rad", 0.0, "cosine amplitude", fit_scale=1e-6),
        Parameter("period_rad", "rad", 1.9e-3, "period of the error in q1"),
    )

    def motor_angles(self, points):
        phase = 2 * np.pi * points.q[:, 0] / self.period_rad
        d = np.zeros_like(points.q)
        d[:, 0] = self.sin_rad * np.sin(phase) + self.cos_rad * np.cos(phase)
        return d


class WavelengthDrift(Effect):
    """The laser's vacuum wavelength drifts slowly (an unstabilised laser warming up): every
    interferometer's scale changes by rate * t, dead path included."""
    name = "wavelength_drift"
    summary = "relative wavelength drift, linear in time"
    parameters = (Parameter("rate_per_s", "1/s", 0.0, "relative drift rate", fit_scale=1e-11),)

    def optics(self, points, optics):
        for a in optics.n_air:
            optics.n_air[a] = optics.n_air[a] * (1.0 + self.rate_per_s * points.t_s)


class DirectionalBacklash(Effect):
    """Motor 2's gearing has backlash: it sits h further along its last move's direction."""
    name = "directional_backlash"
    summary = "motor 2 sits backlash_rad * sign(last move) from its encoder's reading"
    parameters = (Parameter("backlash_rad", "rad", 0.0, "half the backlash", fit_scale=1e-6),)

    def motor_angles(self, points):
        d = np.zeros_like(points.q)
        d[:, 1] = self.backlash_rad * points.move_direction[:, 1]
        return d


class MirrorStep(Effect):
    """The X mirror slips once (a knock, a relaxing glue joint): the X reading steps."""
    name = "mirror_step"
    summary = "the X reading steps by step_m at moment_s"
    parameters = (Parameter("step_m", "m", 0.0, "step of the X reading", fit_scale=10e-9),
                  Parameter("moment_s", "s", 3600.0, "when the mirror slipped"))

    def optics(self, points, optics):
        shift_reading(optics, "x", self.step_m * (points.t_s > self.moment_s))


class QuadraticForceY(Effect):
    """A lateral force along Y proportional to the square of the coil current (a ferrite core
    saturating off-axis): a quadratic force term on Y."""
    name = "quadratic_force_y"
    summary = "lateral force k * I^2 along world Y (I: mean coil current)"
    parameters = (Parameter("k_N_per_A2", "N/A^2", 0.0, "force per squared ampere",
                            fit_scale=0.05),)

    def wrench(self, points):
        w = np.zeros((points.t_s.shape[0], 6))
        w[:, 1] = self.k_N_per_A2 * np.mean(points.currents_A, axis=1) ** 2
        return w


# The generated out-of-library cases: (case, scenario, baseline model effects, injected effect
# and its values, the variable the term depends on, a scenario change). Quiet laboratory
# (quiet/gravity-sag, quiet/magnetic-force for the force) and, for the hard cases where time
# and temperatures climb together, paper-thermal on a symmetric portal frame.
PORTAL = {"loop_drift": {"frame_arm_m": [0.0, 0.0]}}
CASES = {
    "periodic-encoder": ("quiet/gravity-sag", ["geometric_errors", "gravity_sag"], PeriodicEncoder,
                         {"sin_rad": 0.5e-6}, "q1_rad", None),
    "wavelength-drift": ("quiet/gravity-sag", ["geometric_errors", "gravity_sag"], WavelengthDrift,
                         {"rate_per_s": 1e-10}, "t_s", None),
    "backlash": ("quiet/gravity-sag", ["geometric_errors", "gravity_sag"], DirectionalBacklash,
                 {"backlash_rad": 1e-6}, "dir_q2", None),
    "mirror-step": ("quiet/gravity-sag", ["geometric_errors", "gravity_sag"], MirrorStep,
                    {"step_m": 40e-9, "moment_s": 3000.0}, "t_s", None),
    "quadratic-force": ("quiet/magnetic-force", ["geometric_errors", "magnetic_force"],
                        QuadraticForceY, {"k_N_per_A2": 0.1}, "F_N", None),
}
PORTAL_CASES = {
    "portal-wavelength-drift": ("paper-thermal", None, WavelengthDrift, {"rate_per_s": 1e-10},
                                "t_s", PORTAL),
    # in the X/Y session at the benchmark's scale (0.03: 0-3900 s)
    "portal-mirror-step": ("paper-thermal", None, MirrorStep,
                           {"step_m": 40e-9, "moment_s": 2000.0}, "t_s", PORTAL),
}


def simulate_case(case: tuple, scale: float | None = None):
    """(df, meta, baseline effects, the known constants) of a case: its scenario with the
    injected effect on (``scale``: default the scenario's reduced scale)."""
    from deltatwin.calibration.physics.model import model_effects
    from deltatwin.twin.effects import make_effect
    from deltatwin.twin.scenario import Scenario

    scenario, baseline, cls, values, _, changes = case
    sc = Scenario.load(scenario)
    for e in sc.effects:
        for k, v in ((changes or {}).get(e.name) or {}).items():
            e.values[k] = v
            setattr(e, k, np.asarray(v, dtype=np.float64) if np.ndim(v) else v)
    sc.effects.append(make_effect(cls, values))
    sc.hidden = None
    df, meta = sc.simulate(sc.reduced_scale if scale is None else scale)
    if baseline is None:       # every library effect of the scenario that has a model form
        baseline = [e.name for e in sc.effects[:-1] if e.name in model_effects()]
    # what a laboratory knows: the parameters a fit does not adjust, at the scenario's values
    known = {e.name: {p.name: e.values[p.name] for p in e.parameters if p.fit_scale is None}
             for e in sc.effects[:-1] if e.name in baseline}
    return df, meta, baseline, known


def run_case(case: tuple, workdir, scale: float | None = None, max_claims: int = 2) -> dict:
    """The researcher's loop on one case: fit the baseline and diagnose; while a library effect
    is claimed (at most ``max_claims``) add it and diagnose again; then write the effect the
    diagnosis proposes (``deltatwin effect new --from``) and fit with it, and fit with the
    researcher's own effect (the injected class, its constants known). Returns the scores; the
    noise floor (the twin's truth) is what no model can beat."""
    from pathlib import Path

    from deltatwin.calibration.diagnosis.diagnose import diagnose
    from deltatwin.calibration.physics.fit import PhysicsFit
    from deltatwin.commands.effect import camel, skeleton

    df, meta, baseline, known = simulate_case(case, scale)
    cls, expected = case[2], case[4]
    model, claims, start = list(baseline), [], dict(known)
    while True:
        fit = PhysicsFit(model, start=start).fit(df, meta)
        d = diagnose(fit)
        if not claims:
            first = (fit, d)
        if d["missing_effect"] is None or len(claims) == max_claims:
            break
        claims.append(d["missing_effect"])
        model.append(d["missing_effect"])
    named = [v["variable"] for v in d["unexplained"]["depends_on"]]
    form = d["unexplained"].get("form") or []
    main_axis = max(form, key=lambda f: f["val_rms_nm"]) if form else None
    floor = meta["truth"]["noise_floor_nm"]
    out = {"rows": len(df), "baseline_err90_nm": first[0].val_["all"]["err_p90"],
           "claimed": claims, "named": named,
           "named_first": bool(named) and named[0] == expected and d["missing_effect"] is None,
           "form": form, "form_explained": main_axis["explained_fraction"] if main_axis else 0.0,
           "diagnosis": d, "floor_nm": max(floor.values()), "model": model}
    own = PhysicsFit(model + [cls], start={**start, cls.name: case[3]}).fit(df, meta)
    out["own_err90_nm"] = own.val_["all"]["err_p90"]
    out["proposed_err90_nm"] = float("nan")
    if form:
        name = f"proposed_{cls.name}"
        path = Path(workdir) / f"{name}.py"
        path.write_text(skeleton(name, d))
        proposed = PhysicsFit(model + [f"{path}:{camel(name)}"], start=start).fit(df, meta)
        out["proposed_err90_nm"] = proposed.val_["all"]["err_p90"]
    return out
