"""Exact arc derivatives (IDAS, the stop time through the implicit function theorem),
grazing flags, and the Ipopt route: the arc values' derivatives and its convergence test."""

import warnings

import casadi as ca
import numpy as np
import pytest

from identify import SimulationOptions, simulate
from identify.fitting.arcs import arc_functions
from identify.fitting.derivative_check import arc_case
from identify.fitting.driver import FitOptions
from identify.fitting.exact_arcs import ExactArcs, grazing_flags
from identify.fitting.problem import Problem
from identify.fitting.rundata import make_run_data
from identify.model.laws import get_law
from identify.model.params import parameter_set
from identify.model.symbolic import Model
from identify.traces.events import extract_events

V_STICK = 1e-5
MODEL = Model(get_law("exponential"))


def _traces(conditions, v_stick, travel_um=6.0):
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k, nb, fp in conditions:
            run = simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                           travel_um=travel_um, stick_speed_m_per_s=v_stick,
                           options=SimulationOptions(record=False))
            out.append(run.sample(noise_nm=0.0, seed=0, name=f"k{k:g}"))
    return out


@pytest.fixture(scope="module")
def fast_case():
    """Fast slips, stopped by the stick option."""
    return arc_case("fast", _traces([(2.13, 5, 100), (20.3, 30, 30)], V_STICK), v_stick=V_STICK)


@pytest.fixture(scope="module")
def slow_case():
    """The equations as written: slips end at a reversal, after a creep tail."""
    return arc_case("slow", _traces([(2.13, 5, 10)], 0.0, travel_um=8.0), v_stick=0.0)


@pytest.mark.parametrize("which", ["fast_case", "slow_case"])
def test_exact_arcs_reproduce_the_event_located_slips(which, request):
    """The IDAS arc, stopped where the Newton on the stop time puts v = v_stop, gives the slip length,
    end state and stop time of the event-located (Rosenbrock) arc: the two integrators
    agree to a fraction of a picometre (measured 2e-7 µm), far inside the fit's
    continuity tolerance (1e-6 µm)."""
    case = request.getfixturevalue(which)
    arcs = arc_functions(MODEL)
    exact = ExactArcs(MODEL, arcs.input_names)
    y, J, ok = exact.jacobian(case.A, case.Y, case.rows)
    assert case.A.shape[1] >= 3 and ok.all()
    assert np.abs(y[0] - case.Y[0]).max() < 1e-6  # µm
    assert np.abs(y[1] - case.Y[1]).max() < 1e-7
    assert np.abs(y[2] - case.Y[2]).max() < 1e-4  # ms
    assert np.all(np.isfinite(J[:, list(case.rows)]))


def test_exact_jacobian_carries_the_stop_time(fast_case):
    """Through the implicit function theorem the derivative includes the stop time's
    dependence on the inputs: against central differences of the event-located arcs at tolerance 1e-10,
    the derivatives of the slip length along e0, μmin and A (the well-conditioned ones,
    |J| ~ 1 per unit of scale) agree to 1e-3 relative at IDAS tolerance 1e-10. Leaving the
    stop-time term out moves them by the slip's speed at the stop times dT/da: the
    derivative at a fixed horizon differs by O(1)."""
    case = fast_case
    arcs = arc_functions(MODEL)
    ix = arcs.index
    rows = tuple(ix[n] for n in ("e0_um", "mu_min", "A"))
    exact = ExactArcs(MODEL, arcs.input_names, 1e-10, (1e-10,) * 3)
    _, J, ok = exact.jacobian(case.A, case.Y, rows)
    tight = arc_functions(MODEL, 1e-10, 1e-12)
    _, Jr = tight.evaluate_jacobian(case.A, rows=list(rows), scheme="central", rel_step=1e-5)
    Jr = Jr.reshape(2, case.A.shape[1], arcs.n_in).transpose(0, 2, 1)
    assert ok.all()
    for i in rows:
        rel = np.abs(J[0, i] - Jr[0, i]) / np.abs(Jr[0, i])
        assert rel.max() < 1e-3, (arcs.input_names[i], rel.max())


def test_a_slip_idas_cannot_start_is_integrated_by_cvodes_quietly(capsys):
    """A slip from a fully aged contact pulled far past its holding force starts with an
    acceleration IDAS's initial-condition search (IDACalcIC) fails on; that arc is
    integrated by CVODES, the same values as the event-located arc, with a finite
    Jacobian, and nothing SUNDIALS or CasADi printed about the failure reaches stderr."""
    arcs = arc_functions(MODEL)
    values = dict(parameter_set("FOTAS"), mu_max=0.787718, mu_min=0.441074, tau=0.0757459, A=0.0188585,
                  v_stick=V_STICK)
    # (inputs measured where the 10-run speed benchmark's fit met it)
    A = arcs.inputs(0.00884347e-6, 11.7212e-6, 0.785338, values, 2.13, 30e-6, 10.0, 1)
    Y = arcs.evaluate(A)
    rows = tuple(arcs.index[n] for n in ("e0_um", "state0", "mu_max", "mu_min", "tau", "A"))
    exact = ExactArcs(MODEL, arcs.input_names)
    step, _ = exact.function(0, True, rows, "idas")
    with pytest.raises(RuntimeError, match="IDACalcIC"):
        step(A[list(rows), 0], A[:, 0], Y[2, 0], 0.01)
    capsys.readouterr()
    y, J, ok = exact.jacobian(A, Y, rows)
    assert ok.all() and exact.n_failed == 0
    assert abs(y[0, 0] - Y[0, 0]) < 1e-5 and abs(y[1, 0] - Y[1, 0]) < 1e-6
    assert np.all(np.isfinite(J[:, list(rows)]))
    assert capsys.readouterr().err == ""


def test_grazing_flags_name_each_knife_edge():
    """Bit 0: a stop at a step node; bit 1: a peak speed at the stick threshold; a plain
    slip that stops mid-interval, well above the threshold, is not grazing."""
    arcs = arc_functions(MODEL)
    ix = arcs.index
    values = dict(parameter_set("FOTAS"), v_stick=V_STICK)
    A = arcs.inputs(0.0, 2e-6, 0.77, values, 2.13, 5e-6, 100.0, 2)
    A = np.repeat(A, 3, axis=1)
    period_ms = 10.0
    Y = np.array([[1.0, 1.0, 1.0],  # slip µm
                  [0.5, 0.5, 0.5],  # state at the horizon
                  [0.1, period_ms * (1 + 1e-4), 0.1],  # stop ms: mid-interval, at the first node, mid
                  [0.03, 0.03, V_STICK * 1.01],  # peak speed m/s
                  [0.0, 0.0, 0.0]])
    flags = grazing_flags(MODEL, A, Y, ix)
    assert flags[0] == 0
    assert flags[1] & 1 and not flags[1] & 2
    assert flags[2] & 2 and not flags[2] & 1


def test_arc_values_carry_their_jacobian_for_ipopt(fast_case):
    """Ipopt differentiates the NLP itself (its Lagrangian gradient): the arc-values
    callback has a Jacobian, and it is the Jacobian callback's, entry for entry."""
    runs = [make_run_data(extract_events(tr)) for tr in _traces([(2.13, 5, 100)], V_STICK)]
    truth = dict(parameter_set("FOTAS"), v_stick=V_STICK)
    values = {**MODEL.defaults(truth), "drift_rate": 0.0, "exposure": 0.0}
    prob = Problem(runs, MODEL, values, FitOptions(fixed={"v_stick": V_STICK}, solver="ipopt")).build()
    assert hasattr(prob, "ipopt")  # (building it used to fail: no derivative for the arcs)
    w = prob.initial_w({n: truth[n] for n in prob.theta.names})
    A = prob.arc_inputs(w)
    Asym = ca.MX.sym("A", *A.shape)
    jac = ca.Function("j", [Asym], [ca.jacobian(ca.vec(prob._cb_val(Asym)), ca.vec(Asym))])
    Jfull = np.array(jac(A))
    Jcb = np.array(prob._cb_jac(A))  # 2 × n_in·E
    n_in, E = A.shape
    for e in range(E):
        for r in range(2):
            assert np.allclose(Jfull[5 * e + r, n_in * e:n_in * (e + 1)], Jcb[r, n_in * e:n_in * (e + 1)])
    assert np.count_nonzero(Jfull[[5 * e + r for e in range(E) for r in (2, 3, 4)]]) == 0
    # and Ipopt runs from the truth, naming its status
    res = prob.solve_ipopt(w)
    assert np.isfinite(res["f"]) and isinstance(res["status"], str) and res["iterations"] >= 0
    assert res["solver"] == "ipopt" and res["restoration_iterations"] >= 0


@pytest.mark.parametrize("scheme", ["forward", "exact"])
def test_ipopt_stops_at_the_gauss_newton_test(scheme):
    """Ipopt's own KKT tolerance is on the gradient, which the arcs' integration noise
    keeps above ~1e-3: without the statistical test it ran to its iteration limit after
    reaching the solution. With it, a fit of two noisy runs from the default start ends
    converged (or stalled within tolerance) in a few iterations, where the Gauss–Newton
    SQP ends (measured: ½χ² the same to 1e-4, the estimates within 0.08 standard errors:
    μmin and A are confounded here, |correlation| > 0.99, and move together along the
    valley by 0.6 % of μmin between the two stopping points).

    Its outcome used to depend on the process (9 to 109 iterations, once
    ``Restoration_Failed``): Ipopt was given a gradient with structural zeros, which
    CasADi passed on shifted, the last entries uninitialised memory. With the gradient
    dense both routes end converged in 5-6 iterations, the same in every process."""
    from identify import fit

    runs = [tr.sample(noise_nm=90, seed=i, name=f"r{i}") if hasattr(tr, "sample") else tr
            for i, tr in enumerate(_noisy_runs())]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gn = fit(runs, coating="FOTAS", options=FitOptions(fixed={"v_stick": V_STICK}, threads=1))
        ip = fit(runs, coating="FOTAS", options=FitOptions(fixed={"v_stick": V_STICK}, threads=1,
                                                           solver="ipopt", arc_jacobian=scheme))
    assert ip.solver["success"], ip.solver["status"]
    assert ip.solver["status"] in ("Solve_Succeeded", "Stalled_Within_Tolerance")
    # stopped by the test, not by its limit
    assert ip.solver["iterations"] <= 20, ip.solver["iterations"]  # (measured: 5-6; was 9-109)
    assert "Ipopt" in ip.report()
    assert abs(ip.cost - gn.cost) < 0.01
    for n in ("mu_max", "mu_min", "tau", "A"):
        assert abs(ip[n].value - gn[n].value) < 0.1 * gn[n].stderr, n


def _noisy_runs():
    """Two 15 µm FOTAS runs (2.13 N/m 5 µN 100 Hz; 20.3 N/m 30 µN 30 Hz) under the stick option."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return [simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                         travel_um=15, stick_speed_m_per_s=V_STICK, options=SimulationOptions(record=False))
                for k, nb, fp in [(2.13, 5, 100), (20.3, 30, 30)]]


@pytest.mark.slow
def test_bench_derivatives_prints_every_figure(tmp_path, capsys):
    """``python -m identify bench derivatives`` on the simulated sets: the exact route,
    forward and central differences against the tight reference, the grazing count, the
    cost per arc, and a strict JSON of the same."""
    import json

    from identify.cli import main

    out = tmp_path / "d.json"
    assert main(["bench", "derivatives", "--data", "", "--travel-um", "6", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    for word in ("fast stops", "slow stops", "exact (IDAS", "forward differences", "central differences",
                 "grazing", "ms/arc", "exact vs IDAS differences"):
        assert word in text
    results = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"non-JSON {c}"))
    assert len(results) == 2 and all(r["exact_failed"] == 0 for r in results)


def test_fit_option_exact_puts_the_exact_jacobian_in_the_nlp():
    """``FitOptions(arc_jacobian="exact")``: the NLP's constraint Jacobian carries the
    exact arcs' derivatives, laid out as the differences are (it agrees with the central
    differences' to their own accuracy, ~1e-3 of the largest entry here)."""
    with pytest.raises(ValueError, match="'forward', 'central' or 'exact'"):
        FitOptions(arc_jacobian="adjoint")
    runs = [make_run_data(extract_events(tr)) for tr in _traces([(2.13, 5, 100)], V_STICK)]
    truth = dict(parameter_set("FOTAS"), v_stick=V_STICK)
    values = {**MODEL.defaults(truth), "drift_rate": 0.0, "exposure": 0.0}
    jg = {}
    for scheme in ("exact", "central"):
        prob = Problem(runs, MODEL, values, FitOptions(fixed={"v_stick": V_STICK}, arc_jacobian=scheme)).build()
        prob.jacobian_scheme(scheme, 1e-5)
        w = prob.initial_w({n: truth[n] for n in prob.theta.names})
        jg[scheme] = prob.evaluate(w, jac=True)[3].toarray()
    scale = np.abs(jg["central"]).max()
    assert np.abs(jg["exact"] - jg["central"]).max() < 1e-3 * scale
    assert np.abs(jg["exact"][:, : prob.n_theta]).max() > 0.1 * scale  # (the parameter columns are there)


def _benchmark_slips():
    """Two slips of the 8-run withheld-conditions set's fit (noise seed 0; run 20.3 N/m,
    30 µN, 100 Hz), at the point its solve stopped: its 2nd, whose speed's dip grazes the
    stick threshold (stops in 0.060 ms; 0.192 ms with the threshold 10 % lower, 0.058 ms
    10 % higher), and its 3rd, which creeps for 2 ms."""
    fitted = dict(mu_max=0.7940956112126947, mu_min=0.4816172105270891, tau=0.06534749861756459,
                  A=0.01520074570661423)
    values = {**MODEL.defaults(dict(parameter_set("FOTAS"), v_stick=V_STICK)), **fitted}
    arcs = arc_functions(MODEL)
    cols = [arcs.inputs(x0 * 1e-6, e0 * 1e-6, s0, values, 20.3, 30e-6, 100.0, 1)
            for x0, e0, s0 in ((0.5481897208940896, 1.1538102791059106, 0.726400939337064),
                               (0.9361793462764259, 1.0418206537235744, 0.667892979413385))]
    return arcs, np.hstack(cols)


def test_a_slip_at_a_creep_tails_onset_is_flagged_and_its_neighbours_are_not():
    """The slip whose stop changes branch within 10 % of its stick threshold is flagged
    (bit 3 of the grazing flags, with the arcs to integrate it again); the creeping one
    beside it, the same slip well inside its creep (threshold 30 % lower) or well past
    its fast stop (50 % higher), and slips without the stick option are not."""
    from identify.fitting.creep_onset import creep_onset_mask

    arcs, A = _benchmark_slips()
    Y = arcs.evaluate(A)
    assert Y[2, 0] < 0.1 and Y[2, 1] > 1.5  # (the premise: a fast stop beside a creeping one)
    assert creep_onset_mask(arcs, A).tolist() == [True, False]
    assert creep_onset_mask(arcs, A, Y).tolist() == [True, False]
    iv = arcs.index["v_stick"]
    for factor in (0.7, 1.5):
        B = A.copy()
        B[iv] *= factor
        assert not creep_onset_mask(arcs, B).any()
    B = A.copy()
    B[iv] = 0.0
    assert not creep_onset_mask(arcs, B).any()
    flags = grazing_flags(MODEL, A, Y, arcs.index, arcs)
    assert flags[0] & 8 and not flags[1] & 8
    assert not grazing_flags(MODEL, A, Y, arcs.index)[0] & 8  # (without the arcs: not looked for)


def test_creep_onsets_name_the_slip_for_the_report():
    """:func:`creep_onsets` on a problem names the slip by its run, its number in the run
    and its trigger step, with its stop times at the three thresholds."""
    from types import SimpleNamespace

    from identify.fitting.creep_onset import creep_onsets

    arcs, A = _benchmark_slips()
    prob = SimpleNamespace(E=2, arcs=arcs, arc_inputs=lambda w: A, ev_run=np.array([0, 0]),
                           ev_step=np.array([37.0, 52.0]), ev_k=np.array([20.3, 20.3]),
                           ev_Nb=np.array([30e-6, 30e-6]), ev_fp=np.array([100.0, 100.0]),
                           runs=[SimpleNamespace(name="k20.3_Nb30uN_fp100Hz")])
    (onset,) = creep_onsets(prob, None)
    assert (onset["run"], onset["slip"], onset["trigger_step"]) == ("k20.3_Nb30uN_fp100Hz", 1, 37)
    assert onset["normal_load_uN"] == pytest.approx(30.0)
    assert onset["stop_ms"] < 0.1 < onset["stop_ms_threshold_lower"] and onset["stop_ms_threshold_higher"] < 0.1


def test_the_derivative_check_lists_its_grazing_arcs_by_run_and_slip(fast_case):
    """``bench derivatives`` names each grazing arc by its run and its slip number, with
    its reasons, in its printout and its JSON."""
    from identify.fitting.derivative_check import format_result, grazing_list

    assert len(fast_case.labels) == fast_case.A.shape[1]
    assert fast_case.labels[0] == "k2.13 slip 1" and fast_case.labels[-1].startswith("k20.3 slip ")
    listed = grazing_list(np.array([0, 8, 3]), fast_case.labels[:2])
    assert listed == [dict(arc="k2.13 slip 2", reasons=["stop at a creep tail's onset"]),
                      dict(arc="arc 3", reasons=["stop at a step node", "peak speed at the stick threshold"])]
    errors = dict(rel=1e-3, abs=1e-6, agree=0.9, n=1)
    r = dict(case="c", arcs=3, exact_failed=0, grazing=2, rows=["e0_um"], reltol=1e-10,
             grazing_by_reason={"stop at a step node": 1, "stop at a creep tail's onset": 1}, grazing_arcs=listed,
             ms_per_arc=dict(exact=1.0, forward=1.0, central=1.0),
             **{k: errors for k in ("exact", "forward", "central", "exact_grazing", "forward_grazing",
                                    "central_grazing")})
    text = format_result(r)
    assert "  grazing: k2.13 slip 2 (stop at a creep tail's onset)" in text
    assert "  grazing: arc 3 (stop at a step node, peak speed at the stick threshold)" in text
