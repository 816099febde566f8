"""Shared campaigns simulated by the twin (reduced scale) and the models fitted to them."""
import pytest

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.direct_igm import DirectIGM
from deltatwin.twin.scenario import Scenario
from tests.twin_data import slow_paper_thermal

# The DGM's 217 candidate terms need 219 calibration rows per axis; the tests below drop up to
# 10 of them and fit X on the first 400 rows of the X/Y session: 3 % of the paper's points
# (291 X/Y and 312 Z calibration rows) is the smallest round scale that leaves every test a
# well-posed fit (2.4 % is the bare minimum for the full set).
THERMAL_SCALE = 0.03
# paper-force at 0.2: 4x4x4 calibration and 3x3x3 validation grids, x 5 forces (the shipped
# reduced scale, 0.1, gives 3 levels: on 3 levels a cubic term is aliased with a linear one).
FORCE_SCALE = 0.2


@pytest.fixture(scope="session")
def thermal_data(tmp_path_factory):
    return slow_paper_thermal(tmp_path_factory.mktemp("thermal"), THERMAL_SCALE)


@pytest.fixture(scope="session")
def thermal_dgm(thermal_data):
    return DGM().fit(*thermal_data)


@pytest.fixture(scope="session")
def force_data():
    """The force effect on its own (geometric errors + the coil-magnet force): the model the
    force tests are about, without the thermal drift the DirectIGM does not model."""
    return Scenario.load("quiet/magnetic-force", scale=FORCE_SCALE).simulate(FORCE_SCALE)


@pytest.fixture(scope="session")
def force_igm(force_data):
    return DirectIGM().fit(*force_data)
