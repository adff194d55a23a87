"""The camera's random walk (``drift_walk``): its series in the NLP, what each mode adds to
the plateaus and the staircase slope, its derivatives, the candidate's null, bounds,
priors, and the evidence update of its intensity."""

import math
import warnings

import numpy as np
import pytest

from identify import SimulationOptions, simulate
from identify.fitting.driver import FitOptions, make_run_data
from identify.fitting.problem import Problem
from identify.model.effects import WALK_FLOOR, get_effect
from identify.model.laws import get_law
from identify.model.params import WALK_MODES, parameter_set, walk_names
from identify.model.symbolic import Model
from identify.traces.events import extract_events

V_STICK = 1e-5
TRUTH = dict(parameter_set("FOTAS"), v_stick=V_STICK)
FREE = ("mu_max", "mu_min", "tau", "A")


@pytest.fixture(scope="module")
def runs():
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k, nb, fp in [(2.13, 5, 100), (20.3, 30, 30)]:
            r = simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                         travel_um=10.0, stick_speed_m_per_s=V_STICK, options=SimulationOptions(record=False))
            out.append(make_run_data(extract_events(r.sample(noise_nm=0.0, name=f"k{k:g}"))))
    return out


def _problem(runs, extra_values, free=FREE):
    model = Model(get_law("exponential"))
    values = {**model.defaults(TRUTH), "drift_rate": 0.0, "exposure": 0.0, **extra_values}
    return Problem(runs, model, values, FitOptions(free=free, fixed={"v_stick": V_STICK})).build()


def test_a_mode_adds_its_sine_over_the_run_to_its_own_runs_plateaus_and_slope(runs):
    """walk_2 of the second run: its plateaus move by c·√2·sin(1.5π·t̄/T), its staircase
    slope by the walk's mean slope over the run, c·√2·sin(1.5π)/T per second; the first
    run's rows do not move."""
    c = 30e-9
    null = _problem(runs, {})
    own = _problem(runs, {"walk_2@run:k20.3": c})
    w = null.initial_w({n: TRUTH[n] for n in FREE})
    r0, r1 = null.residuals(w), own.residuals(w)
    g = null.residual_groups()
    p0, _ = g["plateaus"]
    s0, _ = g["slopes"]
    rd = runs[1]
    assert rd.span_s == pytest.approx(own.run_span[1]) and rd.span_s > 1.0
    rows = np.nonzero(null.pl_run == 1)[0]
    shift = c * math.sqrt(2) * np.sin(1.5 * math.pi * null.pl_mean_t[rows] / rd.span_s)
    np.testing.assert_allclose((r0 - r1)[p0 + rows] * rd.sigma / np.sqrt(null.pl_n[rows]), shift, rtol=1e-9,
                               atol=1e-15)
    slope = c * math.sqrt(2) * math.sin(1.5 * math.pi) / rd.span_s / rd.fp  # m per step
    # (the slope row is the model's less the data's)
    assert (r1 - r0)[s0 + 1] * rd.sigma / math.sqrt(rd.s_nn) == pytest.approx(slope, rel=1e-9)
    other = np.r_[p0 + np.nonzero(null.pl_run == 0)[0], s0]
    np.testing.assert_array_equal(r0[other], r1[other])


@pytest.mark.parametrize("mode", [1, 4])
def test_the_walks_jacobian_agrees_with_differences(runs, mode, column_agrees):
    name = f"walk_{mode}@run:k2.13"
    prob = _problem(runs, {}, free=("mu_max", name))
    prob.jacobian_scheme("central", 1e-6, share=False)
    w = prob.initial_w({"mu_max": TRUTH["mu_max"], name: 2e-8})
    column_agrees(prob, w, 1, 1e-3, 1e-6, 1e-8)


def test_the_walks_degrees_of_freedom_run_from_none_to_all_with_its_prior(runs):
    """The candidate bound to the runs: with a tight prior its twelve walk coefficients
    count for nothing, with a flat one for all twelve, in between for some."""
    eff = get_effect("drift_walk", runs)
    free = ("mu_max",) + eff.parameters
    walk = [n for n in eff.parameters if n.startswith("walk")]
    assert len(walk) == 2 * WALK_MODES
    counts = {}
    for sw in (1e-3, 2e-8, 1e-15):
        prob = _problem(runs, {}, free=free)
        prob = Problem(runs, prob.model, prob.values, FitOptions(free=free, fixed={"v_stick": V_STICK},
                                                                 priors=eff.priors(sw))).build()
        w = prob.initial_w({"mu_max": TRUTH["mu_max"], **{n: 0.0 for n in eff.parameters}})
        ev = prob.evaluate(w, jac=True)
        counts[sw] = prob.penalised_counts(ev[0], w, ev)[1]
    n_all = prob.n_effective()
    assert counts[1e-3] == pytest.approx(n_all, abs=1e-3)
    assert counts[1e-15] == pytest.approx(n_all - len(walk), abs=1e-3)
    assert counts[1e-15] < counts[2e-8] < counts[1e-3]


class _Run:
    def __init__(self, name, span_s, kind="events"):
        self.name, self.span_s, self.kind, self.k, self.device = name, span_s, kind, 2.13, ""


def test_the_candidate_frees_a_rate_and_a_walk_per_run_with_the_wiener_priors():
    eff = get_effect("drift_walk", [_Run("a", 4.0), _Run("b", 25.0), _Run("c", 9.0, kind="creep")])
    assert eff.labels == ("a", "b") and len(eff.parameters) == 2 * (1 + WALK_MODES)
    assert all(v == 0.0 for v in eff.null.values()) and set(eff.null) == set(eff.parameters)
    lo, hi = eff.bounds["walk_1@run:a"]
    assert lo < 0 < hi and (lo, hi) == eff.bounds["drift_rate@run:b"]
    assert eff.global_twin == "drift_per_run" and eff.scope == "run"
    from identify.model.scopes import SCOPABLE

    assert set(walk_names()) <= set(SCOPABLE)  # every mode may take a value per run
    # a Wiener process of intensity σ on [0, T]: mode m's coefficient has sd σ·√T/((m − ½)π)
    sd = eff.priors(2e-8)
    assert set(sd) == {f"{n}@run:{r}" for r in "ab" for n in walk_names()}
    assert sd["walk_1@run:b"] == pytest.approx(2e-8 * 5.0 / (0.5 * math.pi))
    assert sd["walk_3@run:a"] == pytest.approx(2e-8 * 2.0 / (2.5 * math.pi))
    # unbound (no runs): no priors, nothing to free
    assert get_effect("drift_walk").priors() == {}


def test_the_series_has_the_variance_of_a_wiener_process():
    """Summed over the modes kept, the prior's variance at t is at most σ²·t, within 15 %
    of it past the first fifth of the run (the wander of the first instants is in the
    modes left out), and exactly σ²·T less the share the left-out modes hold (under 4 %)
    at t = T."""
    T, sig = 10.0, 3e-8
    eff = get_effect("drift_walk", [_Run("a", T)])
    sd = eff.priors(sig)
    t = np.linspace(0.2 * T, T, 20)
    var = sum(sd[f"walk_{m}@run:a"] ** 2 * 2 * np.sin((m - 0.5) * math.pi * t / T) ** 2
              for m in range(1, WALK_MODES + 1))
    assert np.all(var <= sig**2 * t * (1 + 1e-12)) and np.all(var >= 0.85 * sig**2 * t)
    kept = sum(1 / (m - 0.5) ** 2 for m in range(1, WALK_MODES + 1)) / (math.pi**2 / 2)
    assert var[-1] == pytest.approx(sig**2 * T * kept, rel=1e-9) and kept > 0.96


def test_the_evidence_update_gives_back_the_intensity_the_coefficients_were_drawn_with():
    rng = np.random.default_rng(4)
    eff = get_effect("drift_walk", [_Run(f"r{i}", 5.0 + i) for i in range(40)])
    sd = eff.priors(2.5e-8)
    values = {n: s * rng.standard_normal() for n, s in sd.items() if n.startswith("walk")}
    assert eff.prior_scale_update(values, len(values)) == pytest.approx(2.5e-8, rel=0.1)
    assert eff.prior_scale_update({n: 0.0 for n in values}, 3.0) == WALK_FLOOR
