"""Forward differences shared among nearly equal arcs while the solver iterates
(identify.fitting.arcs.share_groups, identify.fitting.arcs.SHARE_TOL)."""

import warnings

import numpy as np
import pytest

from identify import FitOptions, fit
from identify.fitting import arcs as arcs_mod
from identify.fitting import covariance as cov_mod
from identify.fitting.arcs import share_groups

from .test_fit import V_STICK, _ForwardFlipped, _traces

FREE = ("mu_max", "mu_min", "tau", "A")


def _columns(n_in=8):
    """Six arcs: x0, e0, state0, two shared parameters, k, Nb, M (rows 0-7)."""
    A = np.zeros((n_in, 6))
    A[0] = [0.0, 5.0, 10.0, 15.0, 20.0, 25.0]  # the block position: different for every arc
    A[1] = [2.0, 2.0002, 2.003, 2.0, 2.0, 2.0]  # e0 (µm)
    A[2] = [0.8, 0.8, 0.8, 0.8, 0.8, 0.8]
    A[3], A[4] = 0.79, 0.48
    A[5] = [2.13, 2.13, 2.13, 20.3, 2.13, 2.13]  # k: the fourth arc is another run's
    A[6], A[7] = 5e-6, 12
    y = np.zeros((5, 6))
    y[4, 4] = 1.0  # the fifth still moving at its horizon
    return A, y


def test_nearly_equal_arcs_of_one_run_share_and_nothing_else_does():
    A, y = _columns()
    typical = np.ones(A.shape[0])
    reps, inv = share_groups(A, y, rows=[1, 2, 3, 4], typical=typical, tol=1e-3)
    group = reps[inv]
    # e0 2.0 and 2.0002 in one cell of the grid 1e-3 × 2 µm wide; x0 does not count
    # without the topography (not among the rows differenced)
    assert group[0] == group[1] == group[5]
    assert len(set(group[[0, 2, 3, 4]])) == 4  # 2.003 a cell further; another k; moving
    # with the block position differenced (the topography), it separates every arc
    reps, inv = share_groups(A, y, rows=[0, 1, 2, 3, 4], typical=typical, tol=1e-3)
    assert len(reps) == 6
    # an arc that failed (NaN) keeps its own differences, and the others still share
    A[1, 5] = np.nan
    reps, inv = share_groups(A, y, rows=[1, 2, 3, 4], typical=typical, tol=1e-3)
    group = reps[inv]
    assert group[5] == 5 and group[0] == group[1] and len(reps) == 5
    # an arc held to its own differences (far from continuity) too
    A[1, 5] = 2.0
    reps, inv = share_groups(A, y, rows=[1, 2, 3, 4], typical=typical, tol=1e-3,
                             own=np.array([False, True, False, False, False, False]))
    group = reps[inv]
    assert group[1] == 1 and group[0] == group[5] != 1 and len(reps) == 5


@pytest.fixture(scope="module")
def small():
    """The two 15 µm runs of test_fit, fitted with and without the sharing."""
    traces = _traces([(2.13, 5, 100), (20.3, 30, 30)])
    return {share: fit(traces, options=FitOptions(fixed={"v_stick": V_STICK}, share_arc_jacobian=share))
            for share in (True, False)}


def test_shared_differences_agree_with_each_arcs_own_at_the_solution(small):
    """At the fit's solution a run's slips repeat one cycle: measured, 9 of the 41 arcs'
    differences stand for all, each within 0.1 % (max 9.3e-4, median 3.8e-4) of the arc's
    own — below the forward differences' own error (95th percentile 6e-3). The values
    are every arc's own."""
    res = small[True]
    prob = res.problem
    A = np.array(prob._arc_inputs(res.w))
    rows, n = prob._cb_jac.rows, A.shape[1]
    own = prob.arcs.evaluate_jacobian(A, rows=rows, rel_step=arcs_mod.SOLVE_REL_STEP, scheme="forward")
    shared = prob.arcs.evaluate_jacobian(A, rows=rows, rel_step=arcs_mod.SOLVE_REL_STEP, scheme="forward",
                                         share=arcs_mod.SHARE_TOL)
    np.testing.assert_array_equal(own[0], shared[0])
    J, Js = (x[1].reshape(2, n, -1)[:, :, rows] for x in (own, shared))
    err = np.abs(Js - J).max(axis=2) / np.abs(J).max(axis=2)
    reps, _ = share_groups(A, own[0], rows, prob.arcs.typical, arcs_mod.SHARE_TOL)
    assert len(reps) <= n // 3, (len(reps), n)
    assert err.max() < 3e-3, err.max()


def test_the_fit_with_shared_differences_ends_where_the_fit_without_does(small):
    """The fit ends on the covariance's central differences
    (Problem.accurate_differences), so both fits end converged within the same statistical
    tolerance (NEAR_TOL: the parameters within 0.045 standard errors in any direction):
    measured, at most 0.035 standard errors apart."""
    a, b = small[True], small[False]
    assert a.solver["success"] and b.solver["success"]
    for name in FREE:
        assert abs(a[name].value - b[name].value) < 0.1 * b[name].stderr, name
        assert a[name].stderr == pytest.approx(b[name].stderr, rel=0.02)


def test_the_fit_ends_on_the_covariances_central_differences(small, monkeypatch):
    """A solve that ended on shared forward differences goes on from there on the
    covariance's central ones (Problem.accurate_differences), the fit's last step: from
    the fit's solution a solve on them ends at once, converged, and the covariance after
    it integrates no arc again (its differences are remembered)."""
    res = small[True]
    prob = res.problem
    w0 = prob.initial_w({"mu_max": 0.75, "mu_min": 0.5, "tau": 0.08, "A": 0.012})
    seen = []
    name = "solve_ipopt" if prob.opts.solver == "ipopt" else "solve_gn"  # (the solver's own solve)
    solve = getattr(prob, name)

    def recording(w, fixed=None, *args):
        cb = prob._cb_jac
        seen.append((prob._cb_jac_shared(), cb.scheme, cb.share))
        return solve(w, fixed, *args)

    monkeypatch.setattr(prob, name, recording)
    sol = prob.solve(w0)
    assert seen == [(True, "forward", arcs_mod.SHARE_TOL)] and sol["shared"] and sol["success"]
    own = prob.accurate_differences(dict(sol, slips_inserted=3))
    assert seen[1:] == [(False, "central", cov_mod.COVARIANCE_SHARE_TOL)]
    assert not own["shared"] and own["success"]
    assert own["slips_inserted"] == 3  # (the fit's records carried)
    # (the SQP tests after a step, Ipopt at its start too: from a solution it may take none)
    assert own["iterations"] >= sol["iterations"] + (prob.opts.solver == "gauss-newton")
    assert prob._cb_jac_shared()  # the option's differences again after it
    n = prob.arcs.n_integrated
    prob.covariance(own["w"])
    assert prob.arcs.n_integrated == n
    seen.clear()
    assert prob.accurate_differences(own) is own and not seen  # nothing to do
    monkeypatch.undo()
    prob.jacobian_scheme("forward", arcs_mod.SOLVE_REL_STEP, share=False)
    end = prob.solve_gn(res.w.copy())
    assert end["success"] and end["iterations"] == 1


def test_a_rejected_step_on_shared_differences_is_taken_again_on_each_arcs_own(small, monkeypatch, tune):
    """A full step on shared differences that fails is computed again at the same point
    on each arc's own forward differences, and then, failing again from a feasible point,
    on central ones (the rung before the sharing): with the forward rows of the wrong
    sign, two iterations more than a solve on central differences from the start, which
    ends at the same point."""
    res = small[True]
    prob, w = res.problem, res.w.copy()
    w[0] += 1e-3
    tune(prob, near_tol=0.0)  # (only the tight convergence rule)
    tune(prob, flat_iters=0)
    prob.jacobian_scheme("central", arcs_mod.SOLVE_REL_STEP)
    w = prob.solve_gn(w, fixed={0: w[0]})["w"]  # feasible, μmax held off
    assert np.abs(prob.evaluate(w)[1]).max() < prob.opts.stop.feas_tol
    prob.jacobian_scheme("forward", arcs_mod.SOLVE_REL_STEP)
    assert prob._cb_jac_shared()
    flipped = _ForwardFlipped(prob._cb_jac.arcs)
    monkeypatch.setattr(prob._cb_jac, "arcs", flipped)
    out = prob.solve_gn(w)
    assert out["central"] and not prob._cb_jac_forward()
    ref = prob.solve_gn(w)
    assert not ref["central"] and ref["success"]
    assert out["success"] and out["iterations"] == ref["iterations"] + 2
    np.testing.assert_allclose(out["w"], ref["w"], rtol=0, atol=1e-12)


def test_arcs_share_only_where_their_constraints_are_near_continuity(small):
    """Per arc (Problem.near_continuity): a slip far from continuity keeps its own
    differences, and so do the slips its constraints touch (the next slip starts from
    the plateau it ends on; the start positions its end state sets); the rest share."""
    prob = small[True].problem
    g = np.zeros(prob.n_g)
    assert prob.near_continuity(g).all()
    nx = prob.ev_next
    e = int(nx[len(nx) // 2])  # a slip with a predecessor and (most likely) a successor
    assert e + 1 in set(nx.tolist()) and prob.n_g == prob.E + nx.size
    g[e] = 2 * arcs_mod.SHARE_FEAS  # its slip length off the plateaus around it
    near = prob.near_continuity(g)
    assert not near[e] and not near[e + 1] and near[e - 1]
    assert near.sum() == prob.E - 2
    g[:] = 0.0
    j = int(np.flatnonzero(nx == e)[0])
    g[prob.E + j] = -2 * arcs_mod.SHARE_FEAS  # the start position of slip e, set by slip e - 1's end
    near = prob.near_continuity(g)
    assert not near[e] and not near[e - 1] and near[e + 1] and near.sum() == prob.E - 2
    # the solver's scheme: the far arcs keep their own differences
    prob.jacobian_scheme("forward", arcs_mod.SOLVE_REL_STEP, share=near)
    assert prob._cb_jac_shared() and prob._cb_jac.own.sum() == 2
    prob.jacobian_scheme("forward", arcs_mod.SOLVE_REL_STEP, share=np.ones(prob.E, bool))
    assert prob._cb_jac.own is None
    # a constraint that could not be evaluated (NaN): its arcs are not near, said without a warning
    g[:] = 0.0
    g[e] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        near = prob.near_continuity(g)
    assert not near[e] and not near[e + 1] and near.sum() == prob.E - 2


def test_the_covariance_on_shared_central_differences_agrees_with_each_arcs_own(small):
    """The covariance shares central differences among arcs within the secant step
    (COVARIANCE_SHARE_TOL): the standard errors agree with those on each arc's own to
    well below 1 % (measured: 0.02 % here, with 27 of the 41 arcs integrated; 0.17 % on
    the 10-run speed set), for every covariance. Each arc's own: the problem of the fit
    with ``share_arc_jacobian=False`` (the same runs and mode sequence), at the same point."""
    res = small[True]
    prob, w = res.problem, res.w
    own_prob = small[False].problem
    assert own_prob.n_w == prob.n_w and all(np.array_equal(a.trigger_steps, b.trigger_steps)
                                            for a, b in zip(prob.runs, own_prob.runs))
    A = np.array(prob._arc_inputs(w))
    reps, _ = share_groups(A, prob.arcs.evaluate(A), prob._cb_jac.rows, prob.arcs.typical,
                           cov_mod.COVARIANCE_SHARE_TOL)
    assert len(reps) < 0.8 * A.shape[1]  # (the test shares something)
    se = {}
    for p, tol in ((prob, cov_mod.COVARIANCE_SHARE_TOL), (own_prob, None)):
        se[tol] = {m: np.sqrt(np.diag(p.covariance(w, robust=m))[:p.n_theta])
                   for m in ("robust", "cluster", "model")}
        assert p._cb_jac.share == tol and p._cb_jac.scheme == "central"
        assert not p._cb_jac_shared()  # (not the solver's shared differences)
    for m, own in se[None].items():
        np.testing.assert_allclose(se[cov_mod.COVARIANCE_SHARE_TOL][m], own, rtol=5e-3, err_msg=m)


def test_a_failed_shared_step_far_out_is_checked_once_and_then_trusted(small, caplog):
    """Far from continuity (|g| >= SHARE_FEAS) a full step on shared differences that
    fails is taken again on each arc's own; when that one too needs the line search,
    the curvature stopped it, not the sharing, and the solve shares again. Measured from
    this start (μmax 30 % low, μmin 10 % high, |g| 0.2 µm): one check, α = 0.12 on the
    arcs' own differences, then shared to the end; each solve converged within NEAR_TOL
    (0.045 standard errors in any direction) of the optimum, so at most ~0.09 apart
    (measured: 0.079 in μmin and A)."""
    import logging

    prob = small[True].problem
    w0 = prob.initial_w({"mu_max": 0.79 * 0.7, "mu_min": 0.48 * 1.1, "tau": 0.067, "A": 0.015})
    assert np.abs(prob.evaluate(w0)[1]).max() > 10 * arcs_mod.SHARE_FEAS
    with caplog.at_level(logging.DEBUG, logger="identify.fitting"):
        prob.jacobian_scheme("forward", arcs_mod.SOLVE_REL_STEP)
        out = prob.solve_gn(w0)
    said = caplog.text
    assert said.count("rejected on shared forward differences") == 1
    assert "sharing again" in said and out["shared"] and out["success"]
    prob.jacobian_scheme("forward", arcs_mod.SOLVE_REL_STEP, share=False)
    ref = prob.solve_gn(w0)
    assert ref["success"] and not ref["shared"]
    se = {n: small[True][n].stderr for n in FREE}
    for j, name in enumerate(prob.theta.names):
        if name in se:
            a, b = (prob.theta.from_scaled(x["w"][: prob.n_theta])[j] for x in (out, ref))
            assert abs(a - b) < 0.1 * se[name], name
