"""Fixtures shared by test folders: small campaigns simulated by the twin."""
import os

if os.environ.get("PYTEST_XDIST_WORKER"):
    # one worker per core (-n auto): a worker's linear algebra on every core would only
    # contend with the other workers (set before numpy loads; the commands the tests run
    # inherit it)
    for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_name, "1")

import pytest  # noqa: E402

from tests.twin_data import slow_paper_thermal  # noqa: E402

# A DGM with three structure sensors (85 candidate terms) needs 87 calibration rows per axis:
# paper-thermal's own reduced scale (2 %: 194 X/Y and 208 Z calibration rows, 96 positions).
SMALL_THERMAL_SCALE = 0.02
SMALL_THERMAL_SENSORS = ("air_x", "base", "arm1", "rod1")


@pytest.fixture(scope="session")
def small_thermal_campaign(tmp_path_factory):
    """(df, meta): the first paper's campaign with three structure sensors and one air sensor,
    2 % of its points over its three days. Shared: copy before changing it."""
    return slow_paper_thermal(tmp_path_factory.mktemp("small_thermal"), SMALL_THERMAL_SCALE,
                                sensors=SMALL_THERMAL_SENSORS)
