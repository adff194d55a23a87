"""A candidate's parameter profiled on every run (identify.diagnosis.regime_profile), and the
diagnosis naming it from there (diagnosis._profile_held), on stand-in profiles whose
points the tests set: the numbers are the withheld rejuvenation set's (dc = 1 µm)."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

import identify.diagnosis.regime_profile as rp
from identify.fitting.regime_check import RegimeCheck

NOISE = {"a": 0.09, "b": 0.09}


def _regime(za, zb, slip_a=0.0, slip_b=0.0):
    runs = [dict(name="a", z=za, slip_z=slip_a, mismatch=za > 2), dict(name="b", z=zb, slip_z=slip_b, mismatch=zb > 2)]
    return dict(runs=runs, df=2, chi2=za * za + zb * zb, mismatched=[r["name"] for r in runs if r["mismatch"]],
                reproduces=not any(r["mismatch"] for r in runs) and slip_a < 2 and slip_b < 2)


# value -> (χ² of the runs fitted, success, lower bound, the left-out runs' reading)
POINTS = {
    1e-7: (3652.6, True, 3652.6, _regime(4.0, 1.0, 1.5)),
    10 ** -6.5: (2959.7, True, 2959.7, _regime(2.0, 1.0)),
    10 ** -6.25: (2744.6, True, 2744.6, _regime(5.0, 2.0)),
    1e-6: (2744.7, True, 2744.7, _regime(0.0, 0.0)),
    10 ** -5.75: (2760.8, True, 2760.8, _regime(0.0, 0.0)),
    10 ** -5.5: (2781.2, False, 2692.5, _regime(0.0, 0.0)),  # not converged: only bounds the profile
}


def _point(v):
    key = min(POINTS, key=lambda k: abs(math.log(k / v)))
    assert abs(math.log(key / v)) < 1e-6, v
    chi2, ok, lower, reg = POINTS[key]
    joint = chi2 + sum(rp.run_distances(reg).values())
    return dict(value=v, chi2=chi2, lower_chi2=lower, success=ok, status="ok" if ok else "Maximum_Iterations_Exceeded",
                continuity_um=1e-4, values={"dc": v, "mu_max": 0.78}, regime=reg, joint=joint, gap_um=0.0078,
                w=np.zeros(3), ev_M=np.zeros(0, int), log=True)


def _fake_chain(calls):
    def chain(task, start, direction, w0, ev_M, n_points=rp.PROFILE_POINTS, include_start=False, beyond=25.0):
        calls.append((start, direction, n_points, include_start))
        vals = [start] if include_start else []
        v = start
        for _ in range(n_points):
            v *= math.sqrt(10.0) ** direction
            if v < 0.9e-7 or v > 4e-6:
                break
            vals.append(v)
        return [_point(x) for x in vals]
    return chain


TASK = SimpleNamespace(effect="rejuvenation", extra=("dc",), nulls={"dc": 2e-8})
START = dict(value=1e-6, w=np.zeros(3), ev_M=np.zeros(0, int))


def test_run_distances_take_the_larger_reading_of_each_run():
    reg = dict(runs=[dict(name="a", z=3.0, slip_z=1.0), dict(name="b", z=0.0, slip_z=2.0),
                     dict(name="c", error="boom", z=None, slip_z=None)])
    assert rp.run_distances(reg) == {"a": 9.0, "b": 4.0}


def test_the_profile_brackets_its_interval_by_points_certainly_beyond_it(monkeypatch):
    """Best at 1 µm; 562 nm fits the runs fitted as well but the left-out runs exclude it,
    1.78 µm the runs fitted exclude: the interval lies between them. The current model
    (χ² 2745.0 + 54.3) is far beyond: significant, its null excluded."""
    calls = []
    monkeypatch.setattr(rp, "profile_chain", _fake_chain(calls))
    final = _regime(7.0, 1.8, 2.5)  # the final model's reading (3 runs parting, here 1)
    out = rp.regime_profile(TASK, START, 2745.0, final, NOISE)
    assert out["value"] == pytest.approx(1e-6)
    lo, hi = out["interval"]
    assert lo == pytest.approx(10 ** -6.25) and hi == pytest.approx(10 ** -5.75)
    assert out["inside"] == (pytest.approx(1e-6), pytest.approx(1e-6))
    c0 = 2745.0 + 49.0 + 3.24
    assert out["current_joint"] == pytest.approx(c0) and out["delta_chi2"] == pytest.approx(c0 - 2744.7)
    assert out["p_value"] < 1e-10 and out["null_excluded"] and out["reproduces"]
    # both directions from the magnitude, then one refinement each side of the best
    assert (1e-6, 1, rp.PROFILE_POINTS, True) in calls and (1e-6, -1, rp.PROFILE_POINTS, False) in calls
    assert sorted(round(math.log10(c[0]), 3) for c in calls[2:]) == [-6.25, -5.75]
    # the left-out runs' largest slips: 2.5·√2·90 nm on run a before, none after, none held out
    assert out["slip_gap_before_um"] == pytest.approx(math.sqrt((2.5 * math.sqrt(2) * 0.09) ** 2 / 2))
    assert out["slip_gap_after_um"] == 0.0 and out["slip_gap_heldout_um"] == 0.0
    assert out["best"]["values"]["dc"] == pytest.approx(1e-6)


def test_a_point_short_of_convergence_does_not_close_the_interval(monkeypatch):
    """A point the solve did not finish only bounds the profile from above: where what it
    could still gain reaches the edge, the side stays open."""
    monkeypatch.setitem(POINTS, 10 ** -5.75, (2760.8, False, 2700.0, _regime(0.0, 0.0)))
    monkeypatch.setattr(rp, "profile_chain", _fake_chain([]))
    out = rp.regime_profile(TASK, START, 2745.0, _regime(7.0, 1.8, 2.5), NOISE)
    assert out["interval"][0] == pytest.approx(10 ** -6.25) and out["interval"][1] is None


def test_no_usable_point_says_so(monkeypatch):
    monkeypatch.setattr(rp, "profile_chain", lambda *a, **k: [dict(value=1e-6, error="ValueError: not finite")])
    out = rp.regime_profile(TASK, START, 2745.0, _regime(7.0, 1.8), NOISE)
    assert out["value"] is None and "no point" in out["error"] and not out["null_excluded"]


# ---------------------------------------------------------------- naming in the diagnosis
def _held(effect="rejuvenation"):
    from identify.diagnosis.records import CandidateResult

    return CandidateResult(effect=effect, ok=True, note="", held_regime=dict(fits=True, reproduces=True),
                           at_magnitude=dict(parameter="dc", value=1e-6), w_at_magnitude=np.zeros(3),
                           ev_M_at_magnitude=np.zeros(0, int))


def _profile_held(monkeypatch, held, own=(), p=1e-13):
    import identify.diagnosis.regime_profile as rprof
    import identify.diagnosis.rounds as D

    def fake_profile(task, start, chi2, final, noise, executor=None, say=None, continuity_um=1e-3):
        return dict(effect=task.effect, parameter="dc", value=1e-6, interval=(5.6e-7, 1.8e-6), inside=(1e-6, 1e-6),
                    delta_chi2=54.5, p_value=p, null_excluded=p < 0.05, reproduces=True, current_joint=2799.2,
                    slip_gap_before_um=0.231, slip_gap_after_um=0.0, slip_gap_heldout_um=0.0, gap_after_um=0.0078,
                    best=dict(values={"dc": 1e-6}))

    monkeypatch.setattr(rprof, "regime_profile", fake_profile)
    monkeypatch.setattr(D, "candidate_tasks", lambda ids, *a, **k: ([None, SimpleNamespace(effect=ids[0])], []))
    screened = []

    def fake_own(law, free, values, runs, say=None, executor=None):
        screened.append(len(runs))
        return [dict(moved=dict(m), start={"tau": 0.04}, reproduces_regime=True) for m in own]

    monkeypatch.setattr(D, "own_screen", fake_own)
    import identify.fitting.regime_check as rc

    monkeypatch.setattr(rc.RegimeRun, "of", classmethod(lambda cls, rd: rd))
    confounded = []
    check = RegimeCheck(runs=[dict(name="a", mismatch=True)], chi2=54.3, df=6, p_value=1e-10)
    current = dict(law="exponential", free=("mu_max", "tau"), values={"tau": 0.04}, chi2=2745.0)
    opts = D.DiagnosisOptions(effects=("rejuvenation", "drift"))
    regime_runs = [SimpleNamespace(name=n, noise_m=9e-8) for n in "abcdef"]
    out, changed = D._profile_held(held, current, ["fitted1", "fitted2"], None, opts, regime_runs, check, None,
                                   lambda m: None, n_cand=13, confounded=confounded)
    return out, confounded, screened, changed


def test_a_significant_profile_no_own_move_matches_names_the_candidate(monkeypatch):
    out, confounded, screened, (c,) = _profile_held(monkeypatch, [_held()])
    assert out["named"] and out["significant"] and confounded == [] and c.named
    assert screened == [8]  # the own moves read on every run: 6 left out, 2 fitted
    assert "Named" in out["note"] and "between 560 nm and 1800 nm" in out["note"]
    assert "named by its profile" in c.note


def test_an_own_move_that_makes_every_run_confounds_the_candidate(monkeypatch):
    out, confounded, _, (c,) = _profile_held(monkeypatch, [_held()], own=[{"tau": 67.4}])
    assert not out["named"] and c.confounded_with == ["tau"] and not c.named
    assert confounded[0]["effects"] == ["rejuvenation"] and "tau ≥ 67.4" in out["note"]


def test_a_profile_that_is_not_significant_names_nothing(monkeypatch):
    out, confounded, screened, _ = _profile_held(monkeypatch, [_held()], p=0.01)
    assert not out["named"] and screened == [] and "not significant" in out["note"]


def test_two_candidates_that_make_the_runs_are_confounded_and_not_profiled(monkeypatch):
    out, confounded, screened, (a, b) = _profile_held(monkeypatch, [_held(), _held("spring_constant")])
    assert not out["named"] and screened == [] and out["effect"] is None
    assert confounded[0]["effects"] == ["rejuvenation", "spring_constant"]
    assert a.confounded_with == ["spring_constant"] and b.confounded_with == ["rejuvenation"]
