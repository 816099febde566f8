"""The fingerprint of the effects' code a fitted model keeps (twin/effects ``code_sha256``)."""
import sys

from deltatwin.twin.effects import LIBRARY, _own_modules, code_sha256, effect_class

MIXIN = '''
import numpy as np


class Scale:
    factor = {factor}
'''

EFFECT = '''
import sys
sys.path.insert(0, {folder!r})
from deltatwin.twin.effects import Effect, Parameter, shift_reading
from lab_mixin_{tag} import Scale


class Tilt(Scale, Effect):
    name = "tilt_{tag}"
    summary = "X reads a tilt in q1"
    parameters = (Parameter("slope_m", "m", 0.0, "slope", fit_scale=1e-9),)

    def optics(self, points, optics):
        shift_reading(optics, "x", self.factor * self.slope_m * points.q[:, 0])
'''


def _tilt(folder, tag, factor):
    (folder / f"lab_mixin_{tag}.py").write_text(MIXIN.format(factor=factor))
    (folder / f"lab_{tag}.py").write_text(EFFECT.format(folder=str(folder), tag=tag))
    return effect_class(f"{folder / f'lab_{tag}.py'}:Tilt")


def test_the_code_fingerprint_follows_the_effects_source_and_its_mixins(tmp_path):
    library = [LIBRARY["geometric_errors"], LIBRARY["loop_drift"]]
    assert code_sha256(library) == code_sha256(list(library))
    assert code_sha256(library) != code_sha256(library[::-1])     # which effect is which
    tilt = _tilt(tmp_path, "fp", 1.0)
    before = code_sha256(library + [tilt])
    assert before != code_sha256(library) and before == code_sha256(library + [tilt])
    # the mixin the effect inherits its factor from, edited: other code
    (tmp_path / "lab_mixin_fp.py").write_text(MIXIN.format(factor=2.0))
    assert code_sha256(library + [tilt]) != before
    # a class whose source cannot be read has no fingerprint
    made = type("Made", (tilt,), {"__module__": "typed_in_a_repl"})
    assert code_sha256([made]) is None


HELPER = '''
def gain():
    return {gain}
'''

USING_HELPER = '''
import sys
sys.path.insert(0, {folder!r})
import numpy as np
from deltatwin.twin.effects import Effect, Parameter, shift_reading
from lab_helper_{tag} import gain


class Sway(Effect):
    name = "sway_{tag}"
    summary = "X reads a sway in q2"
    parameters = (Parameter("slope_m", "m", 0.0, "slope", fit_scale=1e-9),)

    def optics(self, points, optics):
        shift_reading(optics, "x", gain() * self.slope_m * np.asarray(points.q)[:, 1])
'''


def test_the_code_fingerprint_follows_the_researchers_helper_modules_not_installed_ones(
        tmp_path):
    (tmp_path / "lab_helper_hp.py").write_text(HELPER.format(gain=1.0))
    (tmp_path / "lab_hp.py").write_text(USING_HELPER.format(folder=str(tmp_path), tag="hp"))
    sway = effect_class(f"{tmp_path / 'lab_hp.py'}:Sway")
    before = code_sha256([sway])
    assert before is not None and before == code_sha256([sway])
    # numpy, sys and deltatwin are imported too, but only the researcher's helper counts
    found = {}
    _own_modules(sys.modules[sway.__module__], found)
    assert set(found) - {sway.__module__} == {"lab_helper_hp"}
    # the helper the effect's file imports a function from, edited: other code
    (tmp_path / "lab_helper_hp.py").write_text(HELPER.format(gain=2.0))
    assert code_sha256([sway]) != before
