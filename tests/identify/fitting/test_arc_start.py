"""Where slip arcs start: the previous arc's end aged over the rest (shooting variables),
against the mid-interval start, on noiseless data where the difference is visible."""

import warnings

import numpy as np
import pytest

from identify import SimulationOptions, simulate
from identify.fitting.driver import FitOptions, make_run_data
from identify.fitting.mode_sequence.triggers import START_MARGIN, below_top
from identify.fitting.problem import Problem
from identify.model.laws import get_law
from identify.model.params import parameter_set
from identify.model.symbolic import Model
from identify.traces.events import extract_events

V_STICK = 1e-5
TRUTH = dict(parameter_set("FOTAS"), v_stick=V_STICK)


def _noiseless_traces(**tolerances):
    """Two noiseless 15 µm runs (the simulator's tolerances as given)."""
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k, nb, fp in [(2.13, 5, 100), (20.3, 30, 30)]:
            r = simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                         travel_um=15, stick_speed_m_per_s=V_STICK,
                         options=SimulationOptions(record=False, **tolerances))
            out.append(r.sample(noise_nm=0.0, seed=0, name=f"k{k:g}"))
    return out


@pytest.fixture(scope="module")
def noiseless_runs():
    return [make_run_data(extract_events(tr)) for tr in _noiseless_traces()]


def _problem(runs, arc_start):
    model = Model(get_law("exponential"))
    values = {**model.defaults(TRUTH), "drift_rate": 0.0, "exposure": 0.0, "v_stick": V_STICK}
    opts = FitOptions(fixed={"v_stick": V_STICK}, arc_start=arc_start)
    prob = Problem(runs, model, values, opts).build()
    return prob, prob.initial_w({n: TRUTH[n] for n in prob.theta.names})


def test_below_top_is_identity_then_bends_smoothly():
    s = np.linspace(-1, 2, 30001)
    out = below_top(s)
    inner = s <= 1 - 2 * START_MARGIN
    assert np.allclose(out[inner], s[inner], rtol=0, atol=1e-14)
    assert out.max() <= 1 - START_MARGIN + 1e-15  # the arc always starts below the force
    slope = np.diff(out) / np.diff(s)
    assert np.all(np.abs(np.diff(slope)) < 0.01)  # C¹: no jump in the slope
    assert np.all(slope >= -1e-12)  # monotone


@pytest.mark.parametrize("arc_start, worst_nm", [("aged", 0.02), ("mid", None)])
def test_slip_lengths_at_the_truth(noiseless_runs, arc_start, worst_nm):
    """At the true parameters and the frames' plateau levels, the aged start reproduces
    every slip length but a run's first (its initial contact is a variable, here still
    at its start value) to the simulator's precision (measured ≤ 0.007 nm); the mid start
    is off by a tenth of a nanometre (measured 0.06-0.35 nm)."""
    prob, w = _problem(noiseless_runs, arc_start)
    r, g = prob.evaluate(w)
    miss_nm = np.abs(g[: prob.E][prob.ev_next]) * 1e3
    if worst_nm is not None:
        assert miss_nm.max() < worst_nm
        # the shooting constraints hold at the synced start positions
        assert np.abs(g[prob.E :]).max() < 1e-6
        assert prob.n_w == prob.i_s + prob.E
    else:
        assert miss_nm.max() > 0.05
        assert prob.n_w == prob.i_s


@pytest.fixture(scope="module")
def exact_traces():
    """Noiseless traces simulated at tolerance 1e-9 (slip lengths exact to far below the
    arcs' ~0.1 pm): noiseless data should be exact, and at the simulator's default
    tolerance (1e-5) they carry ~1 pm of integration error, which alone moved the
    estimates by ~2e-3 (measured: −2.0e-3 … +2.2e-3 with either trigger encoding)."""
    return _noiseless_traces(reltol=1e-9, abstol=1e-11)


def test_noiseless_data_recover_every_parameter_to_1e4(exact_traces):
    """Issue target: noiseless data recover every free parameter to 1e-4 relative. From a
    start 10 % off (each parameter pushed the way that makes the fit work hardest), the
    interval encoding of the triggers does (measured: 4e-5 at most, τ's); the uniform
    encoding, a Gaussian stand-in for the interval that pulls every trigger towards its
    run's phase, stays biased (measured −2.3e-3 in μmax, −3.8e-3 in τ) — on noisy data
    that pull is small beside the frames' noise. (From 20 % off, with the staged start, this
    two-run set is not fitted by either encoding: the solve ends far off, μmax +270 %.)"""
    from identify import fit

    start = dict(mu_max=TRUTH["mu_max"] / 1.1, mu_min=TRUTH["mu_min"] * 1.1, tau=TRUTH["tau"] * 1.1,
                 A=TRUTH["A"] * 1.1)
    err = {}
    for trigger in ("uniform", "interval"):
        res = fit(exact_traces, coating="FOTAS", options=FitOptions(
            fixed={"v_stick": V_STICK}, start=start, staged_start=False, trigger=trigger))
        assert res.solver["success"], res.solver["status"]
        assert res.solver["trigger"] == trigger, res.start_source  # the interval solve kept
        err[trigger] = {n: abs(res.parameters[n].value / TRUTH[n] - 1) for n in start}
    assert max(err["interval"].values()) < 1e-4, err
    assert max(err["uniform"].values()) > 1e-3, err  # the bias the interval removes


@pytest.mark.slow
def test_noiseless_solve_from_the_truth_stays_there(noiseless_runs):
    """The solver started at the truth on noiseless data. Measured: the aged start stays
    within 1.3e-3 (μmax), 3e-4 (μmin), 5e-3 (τ), 1e-3 (A) (2.1e-3, 3.7e-4, 2.8e-3,
    1.3e-3 with the 1e-4 difference step and the stall rule, 2026-11-22; 2.0e-3, 3.0e-4,
    2.2e-4, 1.1e-3 with the arcs at reltol 1e-7, 2026-11-23); the mid start left for
    −1.2 %, −0.2 %, −18 %, +0.7 %. What is left is the trigger surrogate's pull: the
    uniform-phase residuals cost less a little away from the truth, and a noiseless
    trace pins the start positions only through their ~1 nm effect on slip length: at
    the 46 pm floor a noiseless trace is read with, the solution fits the frames as well
    as the truth (plateau χ² 1.5 against 2.1), and at the simulator's default tolerance
    its slip lengths and the arcs' disagree by ~1-2 pm. Both together keep the uniform
    encoding ~2e-3 off; exact data and the interval encoding meet 1e-4
    (:func:`test_noiseless_data_recover_every_parameter_to_1e4`)."""
    prob, w = _problem(noiseless_runs, "aged")
    sol = prob.solve(w)
    est = prob.params(sol["w"][: prob.n_theta])
    err = {n: abs(est[n] / TRUTH[n] - 1) for n in prob.theta.names}
    assert sol["success"], sol["status"]
    assert max(err.values()) < 1e-2, err

