"""Shared, seeded synthetic campaigns (small) and fitted models for the calibration tests."""
import numpy as np
import pytest

from deltatwin.calibration.blackbox.dgm import DGM
from deltatwin.calibration.blackbox.direct_igm import DirectIGM
from tests.calibration.synthetic import force_campaign, thermal_campaign


@pytest.fixture(scope="session")
def thermal_data():
    df, meta, _ = thermal_campaign(np.random.default_rng(11), n_positions=300, n_xy=900,
                                   n_z=900)
    return df, meta


@pytest.fixture(scope="session")
def thermal_dgm(thermal_data):
    return DGM().fit(*thermal_data)


@pytest.fixture(scope="session")
def force_data():
    return force_campaign(np.random.default_rng(5), n_cal_grid=5, n_val_grid=4)


@pytest.fixture(scope="session")
def force_igm(force_data):
    return DirectIGM().fit(*force_data)
