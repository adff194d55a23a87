"""Optimal experiment design: the information matrix, the plan search, priors, the CLI."""

import itertools
import json

import numpy as np
import pytest

from design.cli import main
from design.experiment import (
    Candidate,
    _effective,
    design_experiment,
    prior_from_fit,
    run_information,
    run_information_parts,
    run_problem,
)
from design.information import _schur_information

SMALL = [Candidate(2.13, 5, 100, 12.0), Candidate(20.3, 30, 30, 12.0), Candidate(2.13, 10, 1000, 12.0)]


@pytest.fixture(scope="module")
def infos():
    """Candidate -> (B, M, summary): information and score covariance."""
    return {c: run_information_parts(c) for c in SMALL}


def test_information_matches_finite_differences():
    """Schur complement of JᵀJ == (dr/dθ)ᵀ(dr/dθ) of the residuals with the nuisances
    re-solved at each θ (central differences)."""
    prob, w, summary = run_problem(SMALL[0])
    assert summary["used"] and summary["kind"] == "events"
    info, _ = _schur_information(prob, w, meat=False)
    n = prob.n_theta
    # differences of re-solved residuals over h = 1e-3 need the re-solves exact: a
    # re-solve stopped within NEAR_TOL leaves residuals off by up to ~0.03, which over 2h
    # is ~15 in a column (measured: 3676 off in JᵀJ against the 402 allowed)
    prob.opts = prob.opts.evolve(near_tol=0.0)

    def profiled(th):
        w1 = w.copy()
        w1[:n] = th
        w1 = prob.solve(w1, fixed={i: th[i] for i in range(n)})["w"]
        return prob.residuals(w1)

    cols = []
    for i in range(n):
        h = 1e-3
        up, dn = w[:n].copy(), w[:n].copy()
        up[i] += h
        dn[i] -= h
        cols.append((profiled(up) - profiled(dn)) / (2 * h))
    J = np.array(cols).T
    assert np.abs(info - J.T @ J).max() <= 2e-3 * np.abs(info).max()


def test_run_information_is_symmetric_psd(infos):
    for c, (I, M, s) in infos.items():
        assert s["used"], (c, s)
        for X in (I, M):
            assert np.allclose(X, X.T)
            assert np.linalg.eigvalsh(X).min() >= -1e-6 * np.abs(X).max()
        np.testing.assert_allclose(run_information(c)[0], I, rtol=1e-9, atol=0)
    assert infos[SMALL[2]][2]["kind"] == "creep"  # steady sliding still informs μ(v)
    # a creep run has no triggers: its score covariance is its information
    np.testing.assert_allclose(infos[SMALL[2]][1], infos[SMALL[2]][0], rtol=1e-6)


def test_phase_locked_triggers_cost_information(infos):
    """The stick-slip runs' slips recur at nearly one phase: their shared trigger error
    makes the sandwich B⁻¹MB⁻¹ wider than B⁻¹ for the trigger-bound static friction."""
    B = sum(infos[c][0] for c in SMALL)
    M = sum(infos[c][1] for c in SMALL)
    fisher = np.sqrt(np.diag(np.linalg.inv(B)))
    sandwich = np.sqrt(np.diag(np.linalg.inv(_effective(B, M))))
    assert sandwich[0] > 1.05 * fisher[0]  # mu_max


def test_no_information_run_says_why():
    I, s = run_information(Candidate(2.13, 0.98, 100, 12.0))
    assert not s["used"] and "stepping" in s["reason"] and not I.any()


def _logdet(combo, infos):
    """log det of a plan's effective information (the sandwich's inverse), relative."""
    scale = np.array([0.796, 0.484, 0.0674, 0.015])  # FOTAS nominal: relative parameters
    E = _effective(sum(infos[c][0] for c in combo), sum(infos[c][1] for c in combo))
    sign, v = np.linalg.slogdet(E * np.outer(scale, scale))
    return v if sign > 0 else -np.inf


def test_d_optimal_beats_every_enumerated_plan(infos):
    plan = design_experiment(3, candidates=SMALL, reference=SMALL[:1] * 3, criterion="D")
    assert plan.enumeration["method"] == "exhaustive enumeration"
    best = _logdet(plan.plan, infos)
    for combo in itertools.combinations_with_replacement(SMALL, 3):
        assert best >= _logdet(combo, infos) - 1e-9
    assert plan.criterion_value == pytest.approx(best, abs=1e-9)
    # the predicted standard errors are the sandwich's; the Fisher ones are reported beside
    E = _effective(sum(infos[c][0] for c in plan.plan), sum(infos[c][1] for c in plan.plan))
    assert [plan.predicted_stderr[n] for n in plan.free] == pytest.approx(np.sqrt(np.diag(np.linalg.inv(E))))
    B = sum(infos[c][0] for c in plan.plan)
    assert [plan.fisher_stderr[n] for n in plan.free] == pytest.approx(np.sqrt(np.diag(np.linalg.inv(B))))


def test_exchange_finds_the_enumerated_optimum():
    exhaustive = design_experiment(3, candidates=SMALL, reference=SMALL[:1], criterion="D")
    exchange = design_experiment(3, candidates=SMALL, reference=SMALL[:1], criterion="D", max_enumerate=0)
    assert exchange.enumeration["method"].startswith("greedy")
    assert exchange.criterion_value == pytest.approx(exhaustive.criterion_value, abs=1e-7)  # sum order


@pytest.mark.parametrize("criterion", ["A", "E"])
def test_other_criteria(criterion):
    plan = design_experiment(2, candidates=SMALL, reference=SMALL[:1] * 2, criterion=criterion)
    assert len(plan.plan) == 2 and np.isfinite(plan.criterion_value)
    assert all(np.isfinite(v) for v in plan.predicted_stderr.values())


def test_unknown_criterion():
    with pytest.raises(ValueError, match="criterion 'Q'"):
        design_experiment(2, candidates=SMALL, criterion="Q")


def _fit_json(tmp_path, coating="FOTAS"):
    names = ("mu_max", "mu_min", "tau", "A")
    se = dict(mu_max=0.002, mu_min=0.01, tau=0.003, A=0.001)
    corr = {a: {b: (1.0 if a == b else (0.5 if {a, b} == {"mu_min", "A"} else 0.0)) for b in names} for a in names}
    js = dict(coating=coating, correlation=corr,
              parameters={n: dict(value=1.0, stderr=se[n], free=True) for n in names})
    p = tmp_path / f"fit_{coating}.json"
    p.write_text(json.dumps(js))
    return p, se


def test_prior_from_fit(tmp_path):
    p, se = _fit_json(tmp_path)
    I = prior_from_fit(p, "FOTAS")
    C = np.linalg.inv(I)
    assert np.sqrt(np.diag(C)) == pytest.approx([se[n] for n in ("mu_max", "mu_min", "tau", "A")])
    assert C[1, 3] / (se["mu_min"] * se["A"]) == pytest.approx(0.5)


def test_prior_lowers_predicted_errors(tmp_path):
    p, _ = _fit_json(tmp_path)
    prior = prior_from_fit(p, "FOTAS")
    without = design_experiment(2, candidates=SMALL, reference=SMALL[:1])
    with_prior = design_experiment(2, candidates=SMALL, reference=SMALL[:1], prior_information=prior)
    assert with_prior.prior_used
    for n in ("mu_max", "mu_min", "tau", "A"):
        assert with_prior.predicted_stderr[n] <= without.predicted_stderr[n] * (1 + 1e-9)


def test_prior_from_another_coating(tmp_path):
    p, _ = _fit_json(tmp_path, coating="OTS")
    with pytest.raises(ValueError, match="coating 'OTS', not FOTAS"):
        prior_from_fit(p, "FOTAS")


def test_cli_bad_input(tmp_path, capsys):
    assert main(["experiment", "--runs", "4", "--criterion", "Q", "--json", str(tmp_path / "o.json")]) == 2
    assert "no such criterion" in capsys.readouterr().err
    p, _ = _fit_json(tmp_path, coating="OTS")
    assert main(["experiment", "--runs", "4", "--prior", str(p), "--json", str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err
    assert "another coating" in err and "Traceback" not in err


def test_cli_writes_plan(tmp_path, capsys, strict_json):
    out = tmp_path / "plan.json"
    code = main(["experiment", "--runs", "2", "--springs", "2.13", "--loads-uN", "5", "10", "--fp", "30", "100",
                 "--travel-um", "12", "--json", str(out), "--plot", str(tmp_path / "plan.png")])
    assert code == 0
    js = strict_json(out)
    assert {"plan", "criterion", "predicted_stderr", "reference_plan"} <= set(js)
    assert len(js["plan"]) == 2
    assert set(js["plan"][0]) == {"spring_constant_N_per_m", "normal_load_uN", "step_frequency_Hz", "travel_um"}
    assert {"plan", "predicted_stderr"} <= set(js["reference_plan"])
    assert (tmp_path / "plan.png").stat().st_size > 1000


@pytest.mark.slow
def test_verification_measures_spread(tmp_path, monkeypatch):
    from design import verification

    plan = design_experiment(2, candidates=SMALL[:2], reference=SMALL[:2][::-1])
    record = tmp_path / "mc.jsonl"
    mc = verification.verify_plans(plan, 3, seed=1, workers=2, record=record)
    assert mc["repeats"] == 3 and mc["plan_failed"] == 0
    for n in plan.free:
        assert np.isfinite(mc["plan_stderr"][n]) and mc["plan_stderr"][n] > 0
        assert np.isfinite(mc["plan_robust_stderr"][n])
    assert len(mc["plan_estimates"]) == 3 and np.isfinite(mc["geometric_mean_ratio"])
    assert "Monte Carlo" in plan.report()
    assert len(record.read_text().splitlines()) == 6
    # a rerun takes every fit from the record: no fit is run again
    monkeypatch.setattr(verification, "_fit_plan", lambda *a: (_ for _ in ()).throw(AssertionError("refit")))
    again = verification.verify_plans(plan, 3, seed=1, workers=1, record=record)
    assert again["plan_stderr"] == mc["plan_stderr"]
    # ... but not under other conditions (another noise level, another coating)
    ctx = lambda noise, jit=verification.JITTER_LOAD: verification._record_context(  # noqa: E731
        plan, noise, verification.STICK_SPEED, jit)
    assert len(verification._load_record(record, ctx(90.0))) == 6
    assert not verification._load_record(record, ctx(60.0))
    assert not verification._load_record(record, ctx(90.0, 0.0))  # nominal loads: other data
    # each fit's own intervals are kept: the coverage of the plan's nominal values
    assert mc["plan_coverage_fits"] == 3 and all(0.0 <= mc["plan_coverage"][n] <= 1.0 for n in plan.free)


def test_verification_interleaves_the_plans():
    from design.verification import _job_order

    keys = ("plan_stderr", "reference_stderr")
    jobs = _job_order(keys, 3, 1, {})
    assert jobs == [("plan_stderr", 0), ("reference_stderr", 0), ("plan_stderr", 1),
                    ("reference_stderr", 1), ("plan_stderr", 2), ("reference_stderr", 2)]
    # a record that holds two plan fits: the reference catches up first, nothing reruns
    done = {("plan_stderr", 1): {}, ("plan_stderr", 2): {}}
    jobs = _job_order(keys, 3, 1, done)
    assert jobs[:2] == [("reference_stderr", 0), ("reference_stderr", 1)]
    assert sorted(jobs) == [("plan_stderr", 2), ("reference_stderr", 0), ("reference_stderr", 1),
                            ("reference_stderr", 2)]


def test_verification_redraws_the_loads():
    from design.verification import _jittered

    plan = [Candidate(2.13, 10.0, 100), Candidate(2.13, 10.0, 100), Candidate(20.3, 40.0, 30)]
    a, b = _jittered(plan, 3, 0.05), _jittered(plan, 3, 0.05)
    assert a == b  # seeded by the repeat
    assert a != _jittered(plan, 4, 0.05)
    for c, j in zip(plan, a):
        assert abs(j.normal_load_uN / c.normal_load_uN - 1) <= 0.05
        assert (j.spring_constant_N_per_m, j.step_frequency_Hz, j.travel_um) == \
            (c.spring_constant_N_per_m, c.step_frequency_Hz, c.travel_um)
    assert a[0].normal_load_uN != a[1].normal_load_uN  # replicates differ
    assert _jittered(plan, 3, 0.0) == plan


def test_cli_bad_jitter(tmp_path, capsys):
    assert main(["experiment", "--runs", "2", "--verify", "2", "--verify-jitter", "1.5",
                 "--json", str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err
    assert "--verify-jitter 1.5" in err and "Traceback" not in err


def test_design_prediction_is_the_fits_covariance():
    """A run's B⁻¹MB⁻¹ is the robust covariance the fit itself would report there; the
    trigger rows are in the order the meat reads them."""
    prob, w, _ = run_problem(SMALL[0])
    t0, t1 = prob.residual_groups()["triggers"]
    runs = prob.trigger_runs()
    assert len(runs) == t1 - t0 and (runs[: prob.n_trig] == prob.ev_run[prob.ev_next]).all()
    B, M = prob.information_parts(w)
    pred = np.linalg.solve(B, M) @ np.linalg.inv(B)
    C = prob.covariance(w, robust="robust")[: prob.n_theta, : prob.n_theta]
    sd = np.sqrt(np.diag(C))
    np.testing.assert_allclose(pred / np.outer(sd, sd), C / np.outer(sd, sd), atol=1e-4)
    # and not the Fisher inverse: the run's slips share their phase error
    assert not np.allclose(np.linalg.inv(B), C, rtol=0.05)


def test_criteria_refuse_an_information_that_is_not_positive_definite():
    """Rounding can leave a singular information with a tiny negative eigenvalue (or two,
    which slogdet's sign misses): D and A must not score it, E ranks it last."""
    from design.experiment import _criterion

    Q = np.linalg.qr(np.random.default_rng(0).normal(size=(4, 4)))[0]
    good = Q @ np.diag([1.0, 2.0, 3.0, 4.0]) @ Q.T
    one_neg = Q @ np.diag([-1e-17, 2.0, 3.0, 4.0]) @ Q.T
    two_neg = Q @ np.diag([-1e-17, -1e-17, 3.0, 4.0]) @ Q.T
    for crit in ("D", "A"):
        assert np.isfinite(_criterion(good, crit))
        assert _criterion(one_neg, crit) == -np.inf and _criterion(two_neg, crit) == -np.inf
    assert _criterion(good, "A") == pytest.approx(-(1 + 1 / 2 + 1 / 3 + 1 / 4))
    assert _criterion(good, "D") == pytest.approx(np.log(24.0))
    assert _criterion(one_neg, "E") < _criterion(good, "E")
