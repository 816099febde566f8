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
