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

USING_HELPERS = '''
import sys
sys.path.insert(0, {folder!r})
import numpy as np
from deltatwin.twin.effects import Effect, Parameter, shift_reading
from lab_helper_{tag} import gain
from lab_consts_{tag} import OFFSET_M
import lab_ns_{tag}.tables


class Sway(Effect):
    name = "sway_{tag}"
    summary = "X reads a sway in q2"
    parameters = (Parameter("slope_m", "m", 0.0, "slope", fit_scale=1e-9),)

    def optics(self, points, optics):
        shift_reading(optics, "x", gain() * lab_ns_{tag}.tables.FACTOR * self.slope_m
                      * np.asarray(points.q)[:, 1] + OFFSET_M)
'''


def test_the_code_fingerprint_follows_the_researchers_helper_modules_not_installed_ones(
        tmp_path):
    """A function, a constant and a namespace package's module the effect's file imports are
    the researcher's code: editing any of them changes the fingerprint; numpy, sys and
    deltatwin are imported too but do not count."""
    (tmp_path / "lab_helper_hp.py").write_text(HELPER.format(gain=1.0))
    (tmp_path / "lab_consts_hp.py").write_text("OFFSET_M = 0.0\n")
    (tmp_path / "lab_ns_hp").mkdir()                 # no __init__.py: a namespace package
    (tmp_path / "lab_ns_hp" / "tables.py").write_text("FACTOR = 1.0\n")
    (tmp_path / "lab_hp.py").write_text(USING_HELPERS.format(folder=str(tmp_path), tag="hp"))
    sway = effect_class(f"{tmp_path / 'lab_hp.py'}:Sway")
    found = {}
    _own_modules(sys.modules[sway.__module__], found)
    assert set(found) == {"lab_helper_hp", "lab_consts_hp", "lab_ns_hp.tables"}
    fingerprints = [code_sha256([sway])]
    assert fingerprints[0] is not None and fingerprints[0] == code_sha256([sway])
    for helper, text in (("lab_helper_hp.py", HELPER.format(gain=2.0)),
                         ("lab_consts_hp.py", "OFFSET_M = 1e-9\n"),
                         ("lab_ns_hp/tables.py", "FACTOR = 2.0\n")):
        (tmp_path / helper).write_text(text)
        fingerprints.append(code_sha256([sway]))
    assert len(set(fingerprints)) == 4                # each edit is other code
