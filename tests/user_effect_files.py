"""The text of a researcher's effect file that the consent tests write: importing it writes
ran.txt beside it, so a test can tell whether its code ran."""

RIPPLE = '''
import pathlib
pathlib.Path(__file__).with_name("ran.txt").write_text("the file's code ran")

from deltatwin.twin.effects import Effect, Parameter, shift_reading


class Ripple(Effect):
    name = "{name}"
    summary = "a ripple on x"
    parameters = (Parameter("amplitude_m", "m", 1e-8, "amplitude"),)

    def optics(self, points, optics):
        shift_reading(optics, "x", self.amplitude_m + 0 * points.q[:, 0])
'''

ANGLES = '''

class Angles(Effect):
    name = "{name}"
    summary = "raises where the encoders are read"

    def motor_angles(self, points):
        raise RuntimeError("no encoder here")
'''


def marker_effect_file(ripple: str, angles: str | None = None) -> str:
    """A file defining ``Ripple`` (a constant shift of x, named ``ripple``) and, with
    ``angles``, ``Angles`` (raising where the encoders are read). Effect names are per
    process: each test gives its own."""
    return RIPPLE.format(name=ripple) + (ANGLES.format(name=angles) if angles else "")
