import warnings

import matplotlib
import pytest

matplotlib.use("Agg")


@pytest.fixture(autouse=True)
def _quiet_deprecations():
    # (dependencies' DeprecationWarnings; CasADi's event notice, printed to stderr rather
    # than warned, is held back by identify.compiled)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        yield
