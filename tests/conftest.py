import warnings

import matplotlib
import pytest

matplotlib.use("Agg")


@pytest.fixture(autouse=True)
def _quiet_deprecations():
    # (dependencies' DeprecationWarnings; CasADi's event notice, printed to stderr rather
    # than warned, is held back by identify.model.compiled)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        yield


def _refuse_constant(name):
    raise ValueError(f"not strict JSON: {name}")


@pytest.fixture
def strict_json():
    """Read a file the toolkit wrote with a strict JSON parser: NaN, Infinity and
    -Infinity (which Python's json accepts by default) fail the test."""
    import json

    def read(path):
        with open(path, encoding="utf-8") as fh:
            return json.loads(fh.read(), parse_constant=_refuse_constant)

    return read


@pytest.fixture
def tune():
    """``tune(prob, **changes)``: the problem's solver options changed through its public
    ``Problem.tuned`` for the rest of the test, restored at its end (module-scoped fits
    are shared between tests)."""
    import contextlib

    with contextlib.ExitStack() as stack:
        yield lambda prob, **changes: stack.enter_context(prob.tuned(**changes))
