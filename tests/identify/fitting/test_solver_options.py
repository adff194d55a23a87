"""The solvers' options: validated fields, ``FitOptions.evolve`` routing a name to the
options that own it, ``Problem.tuned`` restoring them, and Ipopt given what it is told."""

import warnings

import numpy as np
import pytest

from identify import (
    FitOptions,
    GaussNewtonOptions,
    IpoptOptions,
    SimulationOptions,
    StopOptions,
    parameter_set,
    simulate,
)
from identify.fitting.convergence import STAT_TOL
from identify.fitting.problem import Problem
from identify.fitting.rundata import make_run_data
from identify.model.laws import get_law
from identify.model.symbolic import Model
from identify.traces.events import extract_events

V_STICK = 1e-5


def test_the_defaults_are_the_documented_constants():
    opts = FitOptions()
    assert opts.stop == StopOptions() and opts.stop.stat_tol == STAT_TOL
    assert opts.gauss_newton == GaussNewtonOptions() and opts.ipopt == IpoptOptions()
    assert opts.ipopt.nlpsol_options() == {"mu_strategy": "monotone"}


@pytest.mark.parametrize("make, match", [
    (lambda: StopOptions(stat_tol=0), r"StopOptions\.stat_tol = 0: must be a finite number > 0"),
    (lambda: StopOptions(feas_tol=float("nan")), r"StopOptions\.feas_tol"),
    (lambda: StopOptions(stall_iters=0), r"StopOptions\.stall_iters = 0: must be an integer >= 1"),
    (lambda: StopOptions(stall_iters=2.5), r"StopOptions\.stall_iters = 2\.5: must be an integer"),
    (lambda: GaussNewtonOptions(flat_iters=-1), r"GaussNewtonOptions\.flat_iters = -1"),
    (lambda: GaussNewtonOptions(near_tol=-1e-3), r"GaussNewtonOptions\.near_tol = -0\.001: must be .* >= 0"),
    (lambda: IpoptOptions(mu_strategy="fast"), r"mu_strategy = 'fast': choose 'monotone' or 'adaptive'"),
    (lambda: IpoptOptions(extra={"max_iter": 5, "tol": 1}), r"extra sets max_iter, tol, which the toolkit sets"),
    (lambda: FitOptions(stop={"stat_tol": 1}), r"stop = \{'stat_tol': 1\}: must be a StopOptions"),
])
def test_bad_solver_options_name_the_field_and_the_rule(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_evolve_routes_each_name_to_the_options_that_own_it():
    base = FitOptions(max_iter=50)
    new = base.evolve(stall_tol=1.0, near_tol=0.0, mu_strategy="adaptive", max_iter=20)
    assert (new.stop.stall_tol, new.gauss_newton.near_tol, new.ipopt.mu_strategy, new.max_iter) == (
        1.0, 0.0, "adaptive", 20)
    # the rest is kept, and the original is untouched (frozen)
    assert new.stop.stat_tol == base.stop.stat_tol and new.gauss_newton.flat_iters == base.gauss_newton.flat_iters
    assert base.stop.stall_tol != 1.0 and base.max_iter == 50
    # a nested object passed whole and a field of it in one call: the field wins
    both = base.evolve(stop=StopOptions(stat_tol=1e-3), feas_tol=1e-5)
    assert (both.stop.stat_tol, both.stop.feas_tol) == (1e-3, 1e-5)
    with pytest.raises(ValueError, match=r"'stall_toll' is not a field of FitOptions"):
        base.evolve(stall_toll=1.0)
    with pytest.raises(ValueError, match=r"StopOptions\.stall_tol = -1"):
        base.evolve(stall_tol=-1)


@pytest.fixture(scope="module")
def one_run_problem():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tr = simulate("FOTAS", spring_constant_N_per_m=2.13, normal_load_uN=5, step_frequency_Hz=100, travel_um=6,
                      stick_speed_m_per_s=V_STICK, options=SimulationOptions(record=False)).sample(noise_nm=0.0, seed=0)
    truth = dict(parameter_set("FOTAS"), v_stick=V_STICK)
    model = Model(get_law("exponential"))
    values = {**model.defaults(truth), "drift_rate": 0.0, "exposure": 0.0}
    opts = FitOptions(fixed={"v_stick": V_STICK}, solver="ipopt",
                      ipopt=IpoptOptions(mu_strategy="adaptive", extra={"print_user_options": "yes"}))
    prob = Problem([make_run_data(extract_events(tr))], model, values, opts).build()
    return prob, prob.initial_w({n: truth[n] for n in prob.theta.names})


def test_tuned_changes_the_options_for_a_block_and_restores_them(one_run_problem):
    prob, _ = one_run_problem
    before = prob.opts
    with prob.tuned(stall_tol=1.0, max_iter=3) as same:
        assert same is prob and prob.opts.stop.stall_tol == 1.0 and prob.opts.max_iter == 3
        with prob.tuned(stall_tol=2.0):
            assert prob.opts.stop.stall_tol == 2.0 and prob.opts.max_iter == 3
        assert prob.opts.stop.stall_tol == 1.0
    assert prob.opts is before
    with pytest.raises(RuntimeError), prob.tuned(flat_iters=0):
        raise RuntimeError("a solve that fails")
    assert prob.opts is before


def test_ipopt_is_given_its_options_and_a_solve_follows_the_stop_options(one_run_problem):
    prob, w = one_run_problem
    res = prob.solve(w)
    assert res["solver"] == "ipopt" and np.isfinite(res["f"])
    # (Ipopt lists the options it was given, and whether it used them, in its log)
    with open(prob._ipopt_log.path) as log:
        used = [line.split() for line in log if line.strip().startswith("mu_strategy")]
    assert used and used[0][-2:] == ["adaptive", "yes"], used
    # a test that nothing fails stops Ipopt at its first iterate: the stop options reach it
    with prob.tuned(stat_tol=1e9, feas_tol=1e9):
        quick = prob.solve(w)
    assert quick["success"] and quick["iterations"] <= 1, (quick["status"], quick["iterations"])


def test_an_ipopt_option_ipopt_does_not_know_is_refused_when_the_solver_is_built(one_run_problem):
    prob, _ = one_run_problem
    opts = prob.opts.evolve(extra={"no_such_option": 1})
    with pytest.raises(RuntimeError, match="no_such_option"):
        Problem(prob.runs, prob.model, prob.values, opts).build()


def test_ipopt_is_given_a_dense_gradient(one_run_problem):
    """CasADi hands Ipopt a user ``grad_f``'s nonzeros as they are: with structural zeros
    (the last slip's start position of each run enters only the constraints) the later
    entries shifted by one and the last ones were whatever Ipopt's buffer held, so fits
    differed from process to process (9 to 109 iterations with one hash seed or another).
    The gradient is dense."""
    prob, _ = one_run_problem
    grad = prob.ipopt.get_function("nlp_grad_f")  # (the gradient the solver hands Ipopt)
    assert grad.sparsity_out(1).nnz() == prob.n_w == grad.size1_out(1)


def test_ipopt_keeps_the_iteration_limit_of_each_solve(one_run_problem):
    """The iteration limit is read at each solve, so ``Problem.tuned(max_iter=…)`` holds
    without building Ipopt again (the diagnosis's held-magnitude solves rely on it)."""
    prob, w = one_run_problem
    off = np.array(w, float)
    off[: prob.n_theta] *= 1.1
    with prob.tuned(max_iter=2, stat_tol=1e-12, stall_tol=1e-12):
        short = prob.solve(off)
    assert short["status"] == "Maximum_Iterations_Exceeded" and not short["success"]
    assert short["iterations"] == 2
    assert prob.solve(off)["iterations"] > 2  # (and the limit is the problem's own again)


def test_ipopt_asks_the_callers_give_up_as_the_sqp_does(one_run_problem):
    """A caller's ``give_up(iteration, ½χ², promised gain)`` stops Ipopt with
    ``Stopped_Cannot_Matter`` at the iterate it was asked about; ``give_up_far`` is
    asked away from continuity (or with no ``give_up``)."""
    prob, w = one_run_problem
    off = np.array(w, float)
    off[: prob.n_theta] *= 1.1
    asked = []

    def give_up(it, half_chi2, promised):
        asked.append((it, half_chi2, promised))
        return it >= 1

    prob.give_up, prob.give_up_far = None, give_up
    try:
        res = prob.solve(off)
    finally:
        prob.give_up, prob.give_up_far = None, None
    assert res["status"] == "Stopped_Cannot_Matter" and not res["success"]
    assert [a[0] for a in asked] == [0, 1] and res["iterations"] == 1
    # the numbers it is given are the iterate's: ½χ² there, and a gain the step promises
    assert np.isclose(asked[0][1], 0.5 * np.sum(prob.residuals(off) ** 2))
    assert asked[0][2] > 0
    assert np.isclose(res["f"], asked[1][1])


def test_where_ipopt_ends_stuck_the_sqp_goes_on_with_the_iterations_left(one_run_problem, monkeypatch):
    """Ipopt stuck (or failing on its own) with iterations left: the Gauss–Newton SQP goes
    on from its end for the iterations left, and the result says so; stopped by its caller
    or at the iteration limit, it is not handed over."""
    prob, w = one_run_problem
    off = np.array(w, float)
    off[: prob.n_theta] *= 1.05
    ipopt_end = prob.solve_ipopt(off)  # (a point as good as Ipopt's own end)
    stuck = dict(ipopt_end, status="Stuck", success=False, iterations=7)
    monkeypatch.setattr(prob, "solve_ipopt", lambda *a, **k: dict(stuck))
    sqp_limits = []
    solve_sqp = prob._solve_sqp
    monkeypatch.setattr(prob, "_solve_sqp", lambda *a: sqp_limits.append(prob.opts.max_iter) or solve_sqp(*a))
    with prob.tuned(max_iter=30):
        res = prob.solve(off)
    assert sqp_limits == [23] and res["handed_over"] == "Stuck" and res["success"], res["status"]
    assert res["iterations"] > 7 and res["solver"] == "ipopt" and "ipopt_status" in res
    for status in ("Stopped_Cannot_Matter", "Maximum_Iterations_Exceeded"):
        stuck["status"] = status
        sqp_limits.clear()
        assert prob.solve(off)["status"] == status and not sqp_limits


def test_evolve_keeps_a_held_copy_held():
    """A mode-sequence trial holds every parameter (FitOptions refuses that for a fit);
    the solver's hand-over evolves its options for the iterations left, and once failed
    there with "free: at least one parameter must be free"."""
    from identify.fitting.mode_sequence.trials import held_options

    held = held_options(FitOptions(max_iter=50))
    new = held.evolve(max_iter=7, stall_tol=1.0)
    assert new.free == () and new.max_iter == 7 and new.stop.stall_tol == 1.0
    assert held.max_iter == 50  # the original untouched
