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


@pytest.fixture
def column_agrees():
    """``column_agrees(prob, w, i, h, rtol, atol_rel)``: the problem's Jacobian column of
    variable ``i`` at ``w`` (residuals and constraints) against central differences of step
    ``h``, after checking that the variable acts on the data at all."""
    import numpy as np

    def check(prob, w, i, h, rtol, atol_rel):
        _, _, Jr, Jg = prob.evaluate(w, jac=True)
        up, dn = w.copy(), w.copy()
        up[i] += h
        dn[i] -= h
        (ru, gu), (rd, gd) = prob.evaluate(up), prob.evaluate(dn)
        dr, dg = (ru - rd) / (2 * h), (gu - gd) / (2 * h)
        assert max(np.max(np.abs(dr)), np.max(np.abs(dg))) > 1e-3  # the variable acts on the data
        for J, d in ((Jr, dr), (Jg, dg)):
            col = np.asarray(J[:, i].todense()).ravel()
            np.testing.assert_allclose(col, d, rtol=rtol, atol=atol_rel * max(np.max(np.abs(d)), 1.0))

    return check
