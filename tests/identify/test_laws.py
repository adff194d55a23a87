import numpy as np
import pytest
from scipy.integrate import solve_ivp

from identify.laws import LAWS, get_law
from identify.params import PARAMETER_SETS

P = dict(PARAMETER_SETS["FOTAS"])


@pytest.mark.parametrize("name", sorted(LAWS))
@pytest.mark.parametrize("start", ["rejuvenated+", "mid"])
def test_rest_closed_form_solves_the_rate_at_rest(name, start):
    """Each law's closed form (Eq. 11 for the exponential law) integrates its own rate."""
    law = LAWS[name]
    if name == "logarithmic":
        z0 = 0.0 if start.startswith("rej") else 0.02
    else:
        z0 = P["mu_min"] + (1e-3 if start.startswith("rej") else 0.15)
    t = np.linspace(0, 0.5, 11)
    sol = solve_ivp(lambda _t, z: [law.rate(z[0], 0.0, P)], (0, t[-1]), [z0], t_eval=t,
                    rtol=1e-11, atol=1e-13, method="LSODA")
    np.testing.assert_allclose(sol.y[0], law.rest(z0, t, P), rtol=1e-7, atol=1e-10)


def test_exponential_is_eq_11_and_eq_9():
    law = LAWS["exponential"]
    t = np.array([0.0, 0.0674, 1.0])
    psi = law.rest(0.5, t, P)
    np.testing.assert_allclose(psi, 0.796 - (0.796 - 0.5) * np.exp(-t / 0.0674))
    np.testing.assert_allclose(law.static_curve(t, (0.796, 0.484, 0.0674)),
                               0.796 - 0.312 * np.exp(-t / 0.0674))


@pytest.mark.parametrize("name", sorted(LAWS))
def test_steady_state_zeroes_the_rate(name):
    law = LAWS[name]
    for v in (1e-7, 4.6e-6, 1e-3):
        z = law.steady_state(v, P)
        assert abs(law.rate(z, v, P)) < 1e-9 * max(1.0, abs(law.rate(law.aged_state(P), v, P)))


def test_logistic_needs_a_seed():
    law = LAWS["logistic"]
    assert law.rest(P["mu_min"], 10.0, P) == pytest.approx(P["mu_min"])
    assert law.rest(P["mu_min"] + 1e-6, 10.0, P) > P["mu_min"] + 0.1


def test_unknown_law_lists_the_choices():
    with pytest.raises(ValueError, match="exponential, logarithmic, logistic"):
        get_law("power")
