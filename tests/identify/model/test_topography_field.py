"""The rough track (a field of friction along the track, ``topography_field``): its null,
its series, the period it takes from the runs, its priors and the degrees of freedom they
leave, its derivatives in the NLP, and the evidence update of its roughness."""

import math
import warnings

import casadi as ca
import numpy as np
import pytest

from identify import SimulationOptions, simulate
from identify.fitting.driver import FitOptions, make_run_data
from identify.fitting.problem import Problem
from identify.model.effects import (
    MIN_TRACK_LENGTH,
    ROUGHNESS_FLOOR,
    TRACK_LENGTH_FACTOR,
    get_effect,
    roughness_update,
)
from identify.model.laws import get_law
from identify.model.params import TOPO_MODES, parameter_set, topo_field_names
from identify.model.symbolic import Model
from identify.traces.events import extract_events

V_STICK = 1e-5
TRUTH = dict(parameter_set("FOTAS"), v_stick=V_STICK)
FREE = ("mu_max", "mu_min", "tau", "A")
FIELD = topo_field_names()


def test_the_series_is_zero_at_its_null_and_the_sum_of_its_modes_off_it():
    m = Model()
    P = m.defaults(TRUTH)
    x = np.linspace(0, 20e-6, 7)
    eff = get_effect("topography_field")
    assert eff.null == {n: 0.0 for n in FIELD} and len(FIELD) == 2 * TOPO_MODES
    np.testing.assert_array_equal(m.topography(x, {**P, **eff.null}), 0.0)
    P.update(topo_length=30e-6, topo_c2=0.01, topo_s5=-0.004)
    want = 0.01 * np.cos(2 * 2 * np.pi * x / 30e-6) - 0.004 * np.sin(5 * 2 * np.pi * x / 30e-6)
    np.testing.assert_allclose(m.topography(x, P), want, atol=1e-15)
    # every mode, numerically and through CasADi's symbols (as the arcs' right-hand side
    # evaluates it)
    coef = dict(zip(FIELD, np.random.default_rng(4).normal(0, 0.01, len(FIELD))))
    P.update(coef)
    th = 2 * np.pi * x / 30e-6
    want = sum(coef[f"topo_c{j}"] * np.cos(j * th) + coef[f"topo_s{j}"] * np.sin(j * th)
               for j in range(1, TOPO_MODES + 1))
    np.testing.assert_allclose(m.topography(x, P), want, rtol=0, atol=1e-15)
    xs = ca.SX.sym("x")
    f = ca.Function("topo", [xs], [m.topography(xs, P, ops=ca)])
    np.testing.assert_allclose(np.ravel(f(x[None, :])), want, rtol=0, atol=1e-15)
    # each coefficient within the candidate's bounds, which are inside the table's
    for n in FIELD:
        assert eff.bounds[n] == (-0.3, 0.3)


def test_the_withheld_track_has_the_rms_asked_for_on_a_period_not_the_fits():
    vals = get_effect("topography_field").simulation_values(0.01)
    coef = np.array([vals[n] for n in FIELD])
    assert math.sqrt(0.5 * coef @ coef) == pytest.approx(0.01)
    assert vals["topo_length"] == pytest.approx(50e-6)


class _Run:
    def __init__(self, levels_um):
        self.plateau_level0 = np.asarray(levels_um) * 1e-6


def test_the_period_is_longer_than_the_longest_travel():
    eff = get_effect("topography_field", [_Run([0.0, 3.0, 8.0]), _Run([0.0, 12.0])])
    assert eff.length == pytest.approx(TRACK_LENGTH_FACTOR * 12e-6)
    assert eff.fixed_values() == {"topo_length": pytest.approx(15e-6)}
    assert get_effect("topography_field", [_Run([0.0, 1.0])]).length == MIN_TRACK_LENGTH
    assert get_effect("topography_field").fixed_values() == {}  # not bound: the table's period


def test_the_prior_falls_as_one_over_the_mode_and_its_scale_follows_the_evidence():
    eff = get_effect("topography_field")
    pri = eff.priors(0.03)
    assert pri["topo_c1"] == pytest.approx(0.03) and pri["topo_s4"] == pytest.approx(0.0075)
    assert set(pri) == set(FIELD)
    # ρ² = Σ j²(cⱼ² + sⱼ²)/γ
    assert roughness_update({"topo_c1": 0.02, "topo_s2": 0.01}, 2.0) == pytest.approx(
        math.sqrt((0.02**2 + 4 * 0.01**2) / 2))
    assert roughness_update({n: 0.0 for n in FIELD}, 3.0) == ROUGHNESS_FLOOR
    # the other candidates carry none
    assert get_effect("topography").priors() == {} and get_effect("drift").fixed_values() == {}


def test_a_prior_on_a_parameter_that_is_not_free_or_without_a_positive_sd_is_an_error():
    with pytest.raises(ValueError, match="priors: topo_c1 is not free"):
        FitOptions(free=FREE, priors={"topo_c1": 0.01})
    with pytest.raises(ValueError, match="priors: topo_c1 needs a standard deviation > 0"):
        FitOptions(free=FREE + ("topo_c1",), priors={"topo_c1": 0.0})


@pytest.fixture(scope="module")
def runs():
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, (k, nb, fp) in enumerate([(2.13, 5, 100), (20.3, 30, 30)]):
            r = simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                         travel_um=12.0, stick_speed_m_per_s=V_STICK, options=SimulationOptions(record=False))
            out.append(make_run_data(extract_events(r.sample(noise_nm=20.0, seed=i, name=f"k{k:g}"))))
    return out


def _problem(runs, free, priors=None, values=None):
    model = Model(get_law("exponential"))
    vals = {**model.defaults(TRUTH), "drift_rate": 0.0, "exposure": 0.0, "topo_length": 15e-6, **(values or {})}
    return Problem(runs, model, vals, FitOptions(free=free, fixed={"v_stick": V_STICK},
                                                 priors=priors or {})).build()


def test_the_priors_are_rows_of_their_own_and_the_degrees_of_freedom_shrink_with_them(runs):
    eff = get_effect("topography_field")
    free = FREE + FIELD
    counts = {}
    for rho in (1e3, 0.02, 1e-6):
        prob = _problem(runs, free, eff.priors(rho), {"topo_c1": 0.01})
        w = prob.initial_w({**{n: TRUTH[n] for n in FREE}, **{n: 0.0 for n in FIELD}, "topo_c1": 0.01})
        prob.size_arcs(w)
        r = prob.residuals(w)
        p0, p1 = prob.residual_groups()["priors"]
        assert p1 - p0 == len(FIELD) and p1 == r.size
        assert r[p0] == pytest.approx(0.01 / rho)  # topo_c1's row: θ/σ
        chi2, n_eff = prob.penalised_counts(r, w)
        assert chi2 == pytest.approx(float(r[:p0] @ r[:p0]) + prob.chi2_constant())
        counts[rho] = n_eff
    n_all = _problem(runs, free).n_effective()
    assert counts[1e3] == pytest.approx(n_all, abs=1e-3)  # a flat prior: every coefficient counts
    assert n_all - len(FIELD) < counts[1e-6] < counts[0.02] < counts[1e3]
    assert counts[1e-6] == pytest.approx(n_all - len(FIELD), abs=0.05)  # a tight one: none does


@pytest.mark.parametrize("name", ["topo_c1", "topo_s3"])
def test_the_jacobian_of_a_coefficient_agrees_with_differences(runs, name, column_agrees):
    prob = _problem(runs, ("mu_max", name))
    prob.jacobian_scheme("central", 1e-6, share=False)
    w = prob.initial_w({"mu_max": TRUTH["mu_max"], name: 0.01})
    prob.size_arcs(w)
    column_agrees(prob, w, 1, 1e-4, 1e-3, 1e-5)


def test_the_final_model_reports_the_period_its_named_track_was_fitted_on():
    """Measured: the slow rough-track test read the final field on the table's period
    (50 µm) instead of the fit's (36 µm), its coefficients then meaning another track."""
    from types import SimpleNamespace

    from identify.diagnosis.verdict import final_record

    rec = SimpleNamespace(gap=dict(gap_um=0.03, noise_um=0.025), heldout=dict(gap_um=0.031))
    values = {"mu_max": 0.74, "topo_length": 36e-6, "k_scale": 1.0, **{n: 0.01 for n in FIELD}}
    st = SimpleNamespace(final_res=rec, effects=["topography_field"],
                         current=dict(law="exponential", free=("mu_max",) + FIELD, values=values))
    final = final_record(st, True, 1.2, None)
    assert final["values"]["topo_length"] == 36e-6 and "k_scale" not in final["values"]
    st.effects = []
    assert "topo_length" not in final_record(st, True, 1.2, None)["values"]
