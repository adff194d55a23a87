"""The backward step: a named per-run effect tested again against its nested twin once the
rounds end, in the final model (identify.diagnosis.twins_final)."""

import concurrent.futures as cf
from types import SimpleNamespace

import numpy as np
import pytest

from identify.diagnosis.records import CandidateResult
from identify.diagnosis.result import DiagnosisOptions
from identify.diagnosis.twins_final import recheck_twins, twin_task, twin_test
from identify.model.effects import get_effect
from identify.model.scopes import label

RUNS = [SimpleNamespace(name=f"run{i}", kind="events", span_s=10.0 + i, k=2.13, device=None) for i in range(3)]
N_OBS = 3000


class _Executor:
    """Hands each refit task a canned record, and keeps the tasks."""

    def __init__(self, make):
        self.make, self.tasks = make, []

    def submit(self, fn, task):
        self.tasks.append(task)
        fut = cf.Future()
        fut.set_result(self.make(task))
        return fut


def _state(executor, effects=("drift_walk", "load_offset"), candidates=None):
    walk = get_effect("drift_walk", RUNS)
    own = list(walk.parameters)
    values = {"mu_max": 0.8, "mu_min": 0.48, "tau": 0.067, "A": 0.015, "load_offset": 2e-6,
              **{n: 1e-8 * (i + 1) for i, n in enumerate(own)}}
    free = ("mu_max", "mu_min", "tau", "A", *own, "load_offset")
    priors = walk.priors(1e-8)
    final = CandidateResult(effect=None, ok=True, status="Solve_Succeeded", chi2=3000.0, n_eff=4 + 3 + 5.0 + 1,
                            n_obs=N_OBS, free=list(free), law="exponential", values=values,
                            gap=dict(gap_um=0.02, noise_um=0.02), heldout=dict(gap_um=0.021))
    opts = DiagnosisOptions(effects=candidates or ["drift", "drift_per_run", "drift_walk", "load_offset"])
    current = dict(values=values, free=free, law="exponential", w=np.r_[np.zeros(len(free)), 7.0, 8.0],
                   ev_M=np.zeros(1), n_theta=len(free), chi2=final.chi2, n_eff=final.n_eff,
                   bounds=dict(walk.bounds), priors=priors)
    return SimpleNamespace(effects=list(effects), runs=RUNS, opts=opts, current=current, final_res=final,
                           fopts=None, folds=[[0], [1], [2]], threads=1, regime_runs=[], where0=[],
                           executor=executor, n_refits=0, notes=[], say=lambda m: None, rounds=[])


def _twin_record(chi2, n_eff, status="Solve_Succeeded"):
    def make(task):
        values = {**task.values, **{n: 5e-9 for n in task.extra}}
        return CandidateResult(effect=task.effect, ok=True, status=status, chi2=chi2, n_eff=n_eff,
                               n_obs=N_OBS, free=[*task.free, *task.extra], law=task.law, values=values,
                               w=np.arange(len(task.free) + len(task.extra) + 2.0), ev_M=np.zeros(1),
                               priors=task.priors or None, gap=dict(gap_um=0.02, noise_um=0.02),
                               heldout=dict(gap_um=0.0205))
    return make


def test_the_twins_task_is_the_final_model_with_the_walk_taken_out_and_the_rates_warm():
    st = _state(_Executor(None))
    task = twin_task(st, 0)
    walk, per_run = get_effect("drift_walk", RUNS), get_effect("drift_per_run", RUNS)
    modes = set(walk.parameters) - set(per_run.parameters)
    assert task.effect == "drift_per_run"
    assert not modes & set(task.free) and not modes & set(task.extra)
    assert "load_offset" in task.free and set(task.extra) == set(per_run.parameters)
    assert all(task.values[n] == 0.0 for n in modes)  # the walk at its null
    assert not modes & set(task.priors) and not modes & set(task.bounds)
    # the rates start where the walk's refit left them
    assert task.starts[0] == {n: st.current["values"][n] for n in per_run.parameters}
    assert task.folds == st.folds  # measured on the held-out folds: it may become the final model
    np.testing.assert_array_equal(task.w_tail, [7.0, 8.0])
    assert f"drift_rate@run:{label('run0')}" in task.extra


def test_no_check_for_the_last_named_or_a_twin_not_among_the_candidates():
    st = _state(_Executor(None), effects=("load_offset", "drift_walk"))
    assert twin_task(st, 0) is None  # (a global effect has no twin) and the walk is the last named
    assert recheck_twins(st) == []
    st = _state(_Executor(None), candidates=["drift_walk", "load_offset"])
    assert twin_task(st, 0) is None


def test_a_walk_that_adds_nothing_in_the_final_model_gives_way_to_the_rates_and_then_to_one_drift():
    # the per-run rates fit as well as the walk (Δχ² 3 for 5 more effective dof); then one
    # global drift fits far worse than the rates (Δχ² 400 for 2)
    def make(task):
        return _twin_record(3003.0, 8.0)(task) if task.effect == "drift_per_run" else _twin_record(3403.0, 6.0)(task)

    ex = _Executor(make)
    st = _state(ex)
    checks = recheck_twins(st)
    assert [c["twin"] for c in checks] == ["drift_per_run", "drift"]
    assert [c["outcome"] for c in checks] == ["replaced", "kept"]
    assert st.effects == ["drift_per_run", "load_offset"]
    assert st.final_res.effect == "drift_per_run" and st.final_res.chi2 == 3003.0
    assert set(st.current["free"]) >= set(get_effect("drift_per_run", RUNS).parameters)
    assert not any(n.startswith("walk") for n in st.current["free"])
    assert not st.current["priors"]  # the walk's priors went with it
    assert checks[0]["p_value"] == pytest.approx(0.70, abs=0.01)
    assert any("drift_walk replaced by drift_per_run" in n for n in st.notes)
    assert st.n_refits == 2


def test_a_walk_that_fits_beyond_chance_stays_named():
    st = _state(_Executor(_twin_record(3100.0, 8.0)))
    checks = recheck_twins(st)
    assert checks[0]["outcome"] == "kept" and checks[0]["p_value"] < 1e-15
    assert st.effects == ["drift_walk", "load_offset"] and st.final_res.effect is None
    assert any("still fit better" in n for n in st.notes)


def test_a_failed_twin_refit_keeps_the_named_effect_and_says_so():
    st = _state(_Executor(lambda task: CandidateResult(effect=task.effect, ok=False, status="failed: x")))
    checks = recheck_twins(st)
    assert checks == [dict(named="drift_walk", twin="drift_per_run", status="failed: x", outcome="kept")]
    assert st.effects == ["drift_walk", "load_offset"]
    assert any("could not be tested again" in n for n in st.notes)


def test_a_twin_that_fits_as_well_but_did_not_converge_takes_no_place():
    st = _state(_Executor(_twin_record(3003.0, 8.0, status="Maximum_Iterations_Exceeded")))
    checks = recheck_twins(st)
    assert checks[0]["outcome"] == "kept" and checks[0]["p_value"] > 0.5
    assert st.effects == ["drift_walk", "load_offset"] and st.final_res.effect is None
    assert any("did not converge (Maximum_Iterations_Exceeded)" in n for n in st.notes)


def test_no_check_where_runs_were_left_out_for_their_regime_or_the_last_round_failed():
    from identify.diagnosis.records import Round

    ex = _Executor(_twin_record(3003.0, 8.0))
    st = _state(ex)
    st.regime_runs = ["a run left out"]
    assert recheck_twins(st) == [] and not ex.tasks
    assert any("runs were left out for their regime" in n for n in st.notes)
    st = _state(ex)
    st.rounds = [Round(current=CandidateResult(effect=None, ok=False, status="failed: x"))]
    assert recheck_twins(st) == [] and not ex.tasks and st.effects == ["drift_walk", "load_offset"]


def test_the_twin_test_counts_the_extra_effective_dof():
    named = SimpleNamespace(chi2=100.0, n_eff=10.0)
    assert twin_test(named, SimpleNamespace(chi2=100.0, n_eff=10.0), 1000)["keeps"] is False  # dk = 0
    t = twin_test(named, SimpleNamespace(chi2=130.0, n_eff=8.0), 1000)
    assert t["keeps"] and t["extra_dof"] == 2.0 and t["delta_bic"] == pytest.approx(-30 + 2 * np.log(1000))
    assert not twin_test(named, SimpleNamespace(chi2=110.0, n_eff=8.0), 1000)["keeps"]  # p 0.007 but ΔBIC > 0


def test_the_checks_are_in_the_report_and_the_json_and_the_rounds_keep_what_they_named():
    from identify.diagnosis.records import Round
    from identify.diagnosis.result import DiagnosisResult

    cands = [dict(effect=e, ok=True, status="Solve_Succeeded", p_value=1e-9, delta_nll=30.0, delta_aic=-50.0,
                  delta_bic=-40.0, note="", named=True) for e in ("drift_walk", "load_offset")]
    base = CandidateResult(effect=None, ok=True, gap=dict(gap_um=0.03, noise_um=0.02), heldout=dict(gap_um=0.03))
    rounds = [Round(current=base, candidates=tuple(map(CandidateResult.from_dict,
                                                                                      cands)), chosen=c["effect"])
              for c in cands]
    twins = [dict(named="drift_walk", twin="drift_per_run", status="Solve_Succeeded", delta_chi2=3.0, extra_dof=5.0,
                  p_value=0.70, delta_bic=37.0, keeps=False, outcome="replaced"),
             dict(named="drift_per_run", twin="drift", status="failed: x", outcome="kept")]
    res = DiagnosisResult(verdict="adequate", effects=["drift_per_run", "load_offset"], where=[], where_final=[],
                          candidates=[], rounds=rounds, baseline=None,
                          final=dict(gap_um=0.02, heldout_gap_um=0.02), confounded=[], options=DiagnosisOptions(),
                          timing=dict(total_s=1.0, refits=5), twins_final=twins)
    text = res.report()
    assert "[[Twins in the final model]]" in text
    assert "drift_walk               vs drift_per_run            Δχ²      3.0 for   5.0 more dof" in text
    assert "drift_per_run in its place (Solve_Succeeded)" in text and "not tested: the refit failed (failed: x)" in text
    assert "[[Candidates, round 2]] (after adding drift_walk)" in text  # what round 1 named
    back = DiagnosisResult.from_dict(res.to_json())
    assert back.twins_final == twins and back.report() == text
