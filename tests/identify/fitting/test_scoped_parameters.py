"""Per-run and per-device parameters in the NLP: a scoped value acts on its own runs exactly
as the global value would, and nowhere else; its derivatives are right; a fit recovers it."""

import warnings

import numpy as np
import pytest

import identify
from identify import SimulationOptions, simulate
from identify.fitting.driver import FitOptions, make_run_data
from identify.fitting.options import FitError
from identify.fitting.problem import Problem
from identify.model.laws import get_law
from identify.model.params import parameter_set
from identify.model.symbolic import Model
from identify.traces.events import extract_events

V_STICK = 1e-5
TRUTH = dict(parameter_set("FOTAS"), v_stick=V_STICK)
FREE = ("mu_max", "mu_min", "tau", "A")


def _traces(drifts=(0.0, 0.0), k_scales=(1.0, 1.0), noise_nm=0.0, travel_um=12.0):
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for (k, nb, fp), drift, ks in zip([(2.13, 5, 100), (20.3, 30, 30)], drifts, k_scales):
            r = simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                         travel_um=travel_um, stick_speed_m_per_s=V_STICK, params={"k_scale": ks},
                         options=SimulationOptions(record=False))
            out.append(r.sample(noise_nm=noise_nm, seed=len(out), name=f"k{k:g}", drift_rate_m_per_s=drift))
    return out


@pytest.fixture(scope="module")
def runs():
    return [make_run_data(extract_events(tr)) for tr in _traces()]


def _problem(runs, extra_values, free=FREE):
    model = Model(get_law("exponential"))
    values = {**model.defaults(TRUTH), "drift_rate": 0.0, "exposure": 0.0, **extra_values}
    return Problem(runs, model, values, FitOptions(free=free, fixed={"v_stick": V_STICK})).build()


def _rows_of_run(prob, ri):
    """Residual rows (plateaus and staircase slope) and constraint rows (slips) of run ri."""
    g = prob.residual_groups()
    p0, p1 = g["plateaus"]
    s0, _ = g["slopes"]
    rows = list(np.nonzero(prob.pl_run == ri)[0] + p0) + [s0 + ri]
    return np.array(rows), np.nonzero(prob.ev_run == ri)[0]


@pytest.mark.parametrize("base, value, scope", [("drift_rate", 4e-8, "run:k20.3"),
                                                ("k_scale", 1.1, "device:k20.3"),
                                                ("load_offset", 1e-6, "device:k2.13")])
def test_a_scoped_value_acts_on_its_own_runs_as_the_global_value_would(runs, base, value, scope):
    null = _problem(runs, {})
    glob = _problem(runs, {base: value})
    own = _problem(runs, {f"{base}@{scope}": value})
    assert own.scoped_bases == (base,)
    w = null.initial_w({n: TRUTH[n] for n in FREE})
    r0, g0 = null.evaluate(w)
    r1, g1 = glob.evaluate(w)
    r2, g2 = own.evaluate(w)
    inside = 1 if scope.endswith("k20.3") else 0
    for ri, same_as in ((inside, (r1, g1)), (1 - inside, (r0, g0))):
        rows, slips = _rows_of_run(null, ri)
        np.testing.assert_allclose(r2[rows], same_as[0][rows], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(g2[slips], same_as[1][slips], rtol=1e-10, atol=1e-12)
    # and the value does act on its run (a drift on its frames, a spring or load on its slips)
    rows, slips = _rows_of_run(null, inside)
    assert max(np.max(np.abs(r1[rows] - r0[rows])), np.max(np.abs(g1[slips] - g0[slips])) * 1e3) > 1.0


@pytest.mark.parametrize("name", ["drift_rate@run:k20.3", "k_scale@device:k20.3"])
def test_the_jacobian_of_a_scoped_parameter_agrees_with_differences(runs, name, column_agrees):
    prob = _problem(runs, {}, free=("mu_max", name))
    prob.jacobian_scheme("central", 1e-6, share=False)
    w = prob.initial_w({"mu_max": TRUTH["mu_max"], name: 0.0 if name.startswith("drift") else 1.05})
    column_agrees(prob, w, 1, 1e-6, 1e-4, 1e-6)


@pytest.mark.slow
def test_a_fit_recovers_a_drift_of_each_runs_own_sign():
    """Two runs drifting at +40 and −25 nm/s, 90 nm noise: each rate within 3 standard
    errors, and the fit at least as good as the one with the friction parameters held at
    the truth. (Two runs leave μmin and A on a ridge: measured, the free fit sits at
    μmin 0.40, A 0.023 with χ² 10.8 below the truth's, with or without the drifts, so the
    friction parameters are judged by the χ², not by the distance to the truth.)"""
    truth = {"drift_rate@run:k2.13": 4e-8, "drift_rate@run:k20.3": -2.5e-8}
    traces = _traces(drifts=(4e-8, -2.5e-8), noise_nm=90.0, travel_um=20.0)
    res = identify.fit(traces, options=FitOptions(free=FREE + tuple(truth), fixed={"v_stick": V_STICK}))
    held = identify.fit(traces, options=FitOptions(free=tuple(truth),
                                                   fixed={"v_stick": V_STICK, **{n: TRUTH[n] for n in FREE}}))
    assert res.solver["status"] == "Solve_Succeeded"
    assert res.chi2 <= held.chi2 + 1e-6 * held.chi2
    for fit in (res, held):
        for n, v in truth.items():
            assert abs(fit[n].value - v) < 3 * fit[n].stderr, (n, fit[n].value, fit[n].stderr, v)


def test_a_scope_without_a_label_is_one_parameter_per_run_or_device():
    traces = _traces(drifts=(4e-8, -2.5e-8), noise_nm=90.0, travel_um=8.0)
    res = identify.fit(traces, options=FitOptions(free=("mu_max", "drift_rate@run", "load_offset@device"),
                                                  bounds={"drift_rate@run": (-1e-6, 1e-6)},
                                                  fixed={"v_stick": V_STICK}))
    assert res.free == ["mu_max", "drift_rate@run:k2.13", "drift_rate@run:k20.3",
                        "load_offset@device:k2.13", "load_offset@device:k20.3"]
    assert res.problem.opts.bounds["drift_rate@run:k20.3"] == (-1e-6, 1e-6)
    assert "drift_rate@run:k20.3" in res.report()
    # a spring factor for every device but the one with the most runs (ties: the first by name)
    many = identify.fit(traces, options=FitOptions(free=("mu_max", "k_scale@device"), fixed={"v_stick": V_STICK}))
    assert many.free == ["mu_max", "k_scale@device:k20.3"]
    assert res.to_json()["parameters"]["drift_rate@run:k2.13"]["unit"] == "m/s"


def test_a_scoped_name_for_no_run_of_the_data_is_a_clear_error(runs):
    traces = _traces(travel_um=6.0)
    with pytest.raises(FitError, match=r"free: drift_rate@run:nope names no run of the fitted data; "
                                       r"the runs are k2\.13, k20\.3"):
        identify.fit(traces, options=FitOptions(free=("mu_max", "drift_rate@run:nope"),
                                                fixed={"v_stick": V_STICK}))
    with pytest.raises(ValueError, match="cannot take a per-run or per-device value"):
        FitOptions(free=("mu_max", "tau@run:k2.13"))
