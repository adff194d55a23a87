"""Motion blur with the exposure placed on the timestamp (start, centre, end) and the frames
around each slip as observations of their own (``FitOptions.drop_frames``): the simulator's
window, the staircase average, which frames are taken, their model at the null and off
it, their derivatives, and a fit that measures the exposure from them."""

import warnings

import casadi as ca
import numpy as np
import pytest

import identify
from identify import SimulationOptions, simulate
from identify.fitting.nlp_expressions import staircase_blur
from identify.fitting.problem import Problem
from identify.fitting.rundata import drop_frames, make_run_data
from identify.model.errors import ParameterError
from identify.model.laws import get_law
from identify.model.params import exposure_align, parameter_set
from identify.model.symbolic import Model
from identify.traces.events import extract_events

V_STICK = 1e-5
TRUTH = dict(parameter_set("FOTAS"), v_stick=V_STICK)
FREE = ("mu_max", "mu_min", "tau", "A")


def _blur(u, H, a):
    return np.asarray(ca.evalf(staircase_blur(ca.DM(u), H, a))).ravel()


def test_alignment_names_and_shares():
    assert [exposure_align(n) for n in ("start", "centre", "center", "END")] == [0.0, 0.5, 0.5, 1.0]
    assert exposure_align(0.25) == 0.25
    with pytest.raises(ParameterError, match="start, centre, end"):
        exposure_align("middle")
    with pytest.raises(ParameterError, match=r"\[0, 1\]"):
        exposure_align(1.5)


def test_the_staircase_average_against_a_fine_quadrature():
    """Steps at the integers, counted from the step at 0 (the count a timestamp of phase in
    [0, 1) has); a phase outside it, as a shifted clock gives, counts the steps between."""
    u = np.array([0.0, 0.05, 0.3, 0.7, 0.97, -0.04, 1.02])
    for H in (0.0, 0.1, 0.45, 1.0, 2.3):
        for a in (0.0, 0.5, 1.0, 0.3):
            if H == 0:
                np.testing.assert_array_equal(_blur(u, H, a), np.floor(u))
                continue
            s = (np.arange(20000) + 0.5) / 20000
            tau = u[:, None] + H * (s[None, :] - a)
            np.testing.assert_allclose(_blur(u, H, a), np.floor(tau).mean(axis=1), atol=2e-4)


@pytest.fixture(scope="module")
def blurred_run():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = simulate("FOTAS", spring_constant_N_per_m=2.13, normal_load_uN=10.0, step_frequency_Hz=100.0,
                       travel_um=12.0, stick_speed_m_per_s=V_STICK, options=SimulationOptions(record=False))
    return run


def test_the_simulators_window_sits_where_the_alignment_puts_it(blurred_run):
    t = np.array([0.0123, 0.0456, 0.0789])
    T = 2e-3
    for a, name in ((0.0, "start"), (0.5, "centre"), (1.0, "end")):
        tr = blurred_run.sample(times_s=t, exposure_s=T, exposure_align=name)
        s = (np.arange(4000) + 0.5) / 4000 - a
        want = blurred_run.elongation(t[:, None] + T * s[None, :]).mean(axis=1)
        np.testing.assert_allclose(tr.elongation, want, atol=2e-10)  # (the simulator's 256 sub-frames)
    # the default is centred, as before
    np.testing.assert_array_equal(blurred_run.sample(times_s=t, exposure_s=T).elongation,
                                  blurred_run.sample(times_s=t, exposure_s=T, exposure_align="centre").elongation)


def test_the_frames_taken_are_those_within_a_step_of_one_slip_and_not_while_it_moves(blurred_run):
    tr = blurred_run.sample(frame_rate_Hz=530.0, noise_nm=5.0, seed=1)
    ev = extract_events(tr)
    trig = np.asarray(ev.slips["trigger_step"], int)
    fp = tr.step_frequency
    t_s = (trig + ev.step_phase) / fp
    idx, slip = drop_frames(ev, trig)
    d = tr.time_s[idx] - t_s[slip]
    assert idx.size and np.all((d >= -1 / fp) & (d < 1 / fp))
    # each frame near exactly one slip: the count of slips within a step of it
    dd = tr.time_s[:, None] - t_s[None, :]
    near = (dd >= -1 / fp) & (dd < 1 / fp)
    assert np.all(near[idx].sum(axis=1) == 1)
    moving = np.full(trig.size, 0.4e-3)
    idx2, slip2 = drop_frames(ev, trig, moving)
    d2 = tr.time_s[idx2] - t_s[slip2]
    assert not np.any((d2 >= 0) & (d2 < 0.4e-3)) and set(idx2) < set(idx)
    # the plateaus give the frames up: every frame counted once
    rd = make_run_data(ev, drops=True)
    plain = make_run_data(ev)
    assert rd.drops and rd.drop_e.size == idx.size
    assert rd.plateau_n.sum() + rd.drop_e.size >= plain.plateau_n.sum()
    assert rd.plateau_n.sum() + rd.drop_e.size <= len(tr.time_s)


def _problem(runs, free, values=None):
    model = Model(get_law("exponential"))
    vals = {**model.defaults(TRUTH), **(values or {})}
    return Problem(runs, model, vals, identify.FitOptions(free=free, fixed={"v_stick": V_STICK},
                                                          drop_frames=True)).build()


def test_the_null_reads_the_level_on_each_side_and_blur_a_share_of_the_slip(blurred_run):
    """At T = 0 a drop row is the frame against the plateau on its side of the slip (the
    noiseless frames then agree to the arcs' accuracy); a window straddling the slip moves
    the model by the share of it past the slip times the slip's length."""
    tr = blurred_run.sample(frame_rate_Hz=530.0)
    ev = extract_events(tr)
    rd = make_run_data(ev, drops=True)
    prob = _problem([rd], FREE)
    w = prob.initial_w({n: TRUTH[n] for n in FREE})
    prob.size_arcs(w)
    g0, g1 = prob.residual_groups()["drops"]
    assert g1 - g0 == prob.D == rd.drop_e.size > 0
    assert prob.n_observations() == int(rd.plateau_n.sum()) + len(rd.trigger_steps) + prob.D
    # the plateau variables at the data's levels: each drop frame against its own side
    r0 = prob.residuals(w)[g0:g1] * rd.sigma
    assert np.median(np.abs(r0)) < 5e-9
    # a 2 ms exposure ending at the timestamp: frames within 2 ms after a slip move by the
    # share of their window before it times the step's jump, others by the staircase only
    pb = _problem([rd], FREE, {"exposure": 2e-3, "exposure_align": 1.0})
    r1 = pb.residuals(w)[g0:g1] * rd.sigma
    after = (prob.dr_dt > 0) & (prob.dr_dt < 2e-3)
    jump = (rd.plateau_level0[1:] - rd.plateau_level0[:-1])[prob.dr_ev]  # slip length, m
    share = (2e-3 - prob.dr_dt[after]) / 2e-3
    np.testing.assert_allclose((r0 - r1)[after], share * jump[after], atol=0.05 * np.max(jump) + 2 * 46e-9)
    assert np.all(np.abs((r0 - r1)[~after]) <= 46e-9 + 1e-12)


@pytest.mark.parametrize("name,col", [("exposure", 0), ("clock_shift@run", 1)])
def test_the_drop_rows_derivatives_agree_with_differences(blurred_run, name, col, column_agrees):
    tr = blurred_run.sample(frame_rate_Hz=530.0, exposure_s=2e-3, exposure_align="end", noise_nm=20.0, seed=3)
    rd = make_run_data(extract_events(tr), drops=True)
    free = ("exposure", "clock_shift@run:" + tr.name)
    prob = _problem([rd], free, {"exposure_align": 1.0})
    prob.jacobian_scheme("central", 1e-6, share=False)
    w = prob.initial_w({"exposure": 1.5e-3, free[1]: 1e-4})
    prob.size_arcs(w)
    column_agrees(prob, w, col, 1e-4, 1e-4, 1e-6)


@pytest.mark.slow
def test_a_fit_measures_an_exposure_ending_at_the_timestamp_from_the_frames_around_slips():
    """Three runs, 5.3 frames per step (frames at every phase), a 2 ms exposure ending at
    the timestamp, 25 nm: measured, the exposure 1.972 ± 0.034 ms and the 724 drop frames
    at χ² 719; with the exposure held at 0 the same frames give χ² 3089."""
    traces = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, (k, nb) in enumerate([(2.13, 5.0), (2.13, 10.0), (20.3, 30.0)]):
            run = simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=100.0,
                           travel_um=15.0, stick_speed_m_per_s=V_STICK, options=SimulationOptions(record=False))
            traces.append(run.sample(exposure_s=2e-3, exposure_align="end", frame_rate_Hz=530.0, noise_nm=25.0,
                                     seed=i, name=f"r{i}"))
    out = {}
    for blur in (False, True):
        free = FREE + ("clock_shift@run",) + (("exposure",) if blur else ())
        fixed = {"v_stick": V_STICK, **({} if blur else {"exposure": 0.0})}
        res = identify.fit(traces, options=identify.FitOptions(
            free=free, fixed=fixed, drop_frames=True, bounds={"clock_shift@run": (-3e-3, 3e-3)},
            start={"exposure": 1e-3} if blur else {}))
        r = res.problem.residuals(res.w)
        g0, g1 = res.problem.residual_groups()["drops"]
        out[blur] = (res, float(r[g0:g1] @ r[g0:g1]), g1 - g0)
    res, chi2_drops, n = out[True]
    est = res["exposure"]
    # the interval holds the truth, and the drop frames sit at their noise
    assert est.ci95[0] <= 2e-3 <= est.ci95[1]
    assert chi2_drops < n + 4 * np.sqrt(2 * n)
    assert out[False][1] > chi2_drops + 100  # held at 0, the same frames cannot be explained


def test_the_blur_candidate_frees_a_clock_shift_per_run_whose_drop_frames_it_reads():
    from types import SimpleNamespace

    from identify.model.effects import get_effect

    runs = [SimpleNamespace(name="a", kind="events", fp=100.0, drops=True),
            SimpleNamespace(name="b", kind="events", fp=30.0, drops=True),
            SimpleNamespace(name="c", kind="creep", fp=10.0, drops=False)]
    eff = get_effect("motion_blur", runs)
    assert eff.parameters == ("exposure", "clock_shift@run:a", "clock_shift@run:b")
    assert eff.null == {"exposure": 0.0, "clock_shift@run:a": 0.0, "clock_shift@run:b": 0.0}
    assert eff.bounds["clock_shift@run:b"] == pytest.approx((-0.5 / 30, 0.5 / 30))
    # the shifts are nuisances: the exposure alone defines the candidate (its Wald test,
    # its confounding), while the likelihood ratio counts all three
    assert eff.defining == ("exposure",)
    assert get_effect("motion_blur").named(eff.parameters).defining == ("exposure",)
    # runs whose frames around the slips are not observed: T alone, as before
    plain = get_effect("motion_blur", [SimpleNamespace(name="a", kind="events", fp=100.0, drops=False)])
    assert plain.parameters == ("exposure",)
