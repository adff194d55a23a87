"""The diagnosis's report names every refit that ended short of convergence."""

from identify.diagnosis.result import DiagnosisOptions, DiagnosisResult


def _result(rounds):
    return DiagnosisResult(verdict="adequate", effects=[], where=[], where_final=[], candidates=[], rounds=rounds,
                           baseline=None, final=dict(gap_um=0.02, heldout_gap_um=0.02), confounded=[],
                           options=DiagnosisOptions(), timing=dict(total_s=1.0, refits=3))


def _scored(effect, status):
    return dict(effect=effect, ok=True, status=status, p_value=0.5, delta_nll=0.1, delta_aic=1.8, delta_bic=5.0,
                gap_before_um=0.02, gap_after_um=0.02, heldout_gap_before_um=0.02, heldout_gap_after_um=0.02,
                note="")


def test_every_refit_that_ended_short_is_listed_under_the_verdict():
    rounds = [[dict(effect=None, ok=False, status="Solve_Succeeded"),
               _scored("drift", "Solve_Succeeded"), _scored("logarithmic", "Maximum_Iterations_Exceeded"),
               dict(effect="damping", ok=False, status="failed: RuntimeError: x"),
               dict(effect="topography", ok=False, status="not applicable", reason="not applicable: one run")]]
    res = _result(rounds)
    assert [(c["effect"], c["status"]) for c in res.not_converged()] == [
        ("logarithmic", "Maximum_Iterations_Exceeded"), ("damping", "failed: RuntimeError: x")]
    line = next(x for x in res.report().splitlines() if "not converged" in x)
    assert "2 refit(s)" in line and "logarithmic (round 1: Maximum_Iterations_Exceeded)" in line
    assert res.to_json()["not_converged"][0]["effect"] == "logarithmic"


def test_candidate_table_is_in_nm_as_the_summary_and_never_prints_nan():
    missing = dict(_scored("damping", "Solve_Succeeded"), p_value=None, heldout_gap_after_um=float("nan"),
                   heldout_delta_nll=None)
    rep = _result([[dict(effect=None, ok=False, status="Solve_Succeeded"), _scored("drift", "Solve_Succeeded"),
                    missing]]).report()
    header = next(x for x in rep.splitlines() if "Δnll h-o" in x)
    assert "gap nm" in header and "held-out nm" in header and "µm" not in header
    drift = next(x for x in rep.splitlines() if x.strip().startswith("drift"))
    assert "20.0->20.0" in drift  # 0.02 µm, in nm as the summary gives it
    damping = next(x for x in rep.splitlines() if x.strip().startswith("damping"))
    assert "nan" not in damping.lower() and "20.0->–" in damping


def test_an_estimate_on_its_bound_says_so_rather_than_giving_a_value_with_an_error():
    """(a diagnosis showed 'damping -3e-07 N·s/m' as if measured: it is the bound that
    keeps the total damping positive)"""
    from types import SimpleNamespace

    import numpy as np

    from identify.diagnosis.refit_readings import parameter_estimates
    from identify.diagnosis.scores import estimate_text
    from identify.fitting.problem import ThetaMap
    from identify.model.effects import get_effect

    tm = ThetaMap.build(("tau", "c_extra"), {"c_extra": get_effect("damping").bounds["c_extra"]})
    th = np.array([tm.to_scaled({"tau": 0.07, "c_extra": 0.0})[0], tm.lo[1]])
    prob = SimpleNamespace(theta=tm, n_theta=2, covariance=lambda w, robust, evaluated: np.eye(2) * 1e-4)
    est = parameter_estimates(prob, th, None)
    assert est["tau"]["at_bound"] is None and "±" in estimate_text(est["tau"])
    assert est["c_extra"]["at_bound"] == "lower" and est["c_extra"]["bound"] == -3e-7
    text = estimate_text(est["c_extra"])
    assert "at its lower bound" in text and "±" not in text
