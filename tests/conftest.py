import warnings

import matplotlib
import pytest

matplotlib.use("Agg")


@pytest.fixture(autouse=True)
def _quiet_casadi_event_warning():
    # CasADi prints "Event support is experimental" for every event integrator; it is
    # expected here (see README, integrators).
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        yield
