"""Slips the event detection missed are found by the fitted model and inserted."""

import dataclasses
import warnings

import numpy as np
import pytest

from identify import FitOptions, SimulationOptions, fit, simulate
from identify.model.params import parameter_set
from identify.traces.events import extract_events

V_STICK = 1e-5


@pytest.fixture(scope="module")
def events():
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, (k, nb, fp) in enumerate([(2.13, 5, 100), (20.3, 30, 30)]):
            r = simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                         travel_um=15, stick_speed_m_per_s=V_STICK, options=SimulationOptions(record=False))
            out.append(extract_events(r.sample(noise_nm=90, seed=i, name=f"run{i}")))
    return out


def _merge_slip(ev, j):
    """The events of ``ev`` as if slip j had not been detected: its two plateaus one."""
    slips = {k: np.delete(v, j) for k, v in ev.slips.items()}
    pof = ev.plateau_of_frame.copy()
    pof[pof > j] -= 1
    return dataclasses.replace(ev, slips=slips, plateau_of_frame=pof)


def _fit(evs):
    truth = dict(parameter_set("FOTAS"), v_stick=V_STICK)
    return fit(evs, options=FitOptions(fixed={"v_stick": V_STICK}), true_values=truth)


def test_a_missed_slip_is_inserted_at_its_step(events):
    ev = events[1]
    j = len(ev.slips["trigger_step"]) // 2
    removed = int(ev.slips["trigger_step"][j])
    res = _fit([events[0], _merge_slip(ev, j)])
    assert res.solver["slips_inserted"] == 1
    steps = res.problem.runs[1].trigger_steps
    assert len(steps) == len(ev.slips["trigger_step"])
    assert np.min(np.abs(steps - removed)) <= 1
    # solved afresh on the repaired sequence, the warm point only if that looked wrong
    (rec,) = res.solver["restarts"]
    assert rec["slips_inserted"] == 1 and rec["kept"] == ("warm" if rec["fresh_suspect"] else "fresh")
    # with the slip back, the estimates are those of the intact data (well inside 1 σ)
    ref = _fit(events)
    for n in ("mu_max", "mu_min", "tau", "A"):
        assert abs(res[n].value - ref[n].value) < 0.5 * ref[n].stderr, n


def test_nothing_inserted_when_nothing_was_missed(events):
    res = _fit(events)
    assert res.solver["slips_inserted"] == 0
    assert "0 missed slip(s) inserted" in res.report()


class _Stub:
    """A problem whose solves end where a script says (by start: 'fresh' or 'warm')."""

    def __init__(self, ends):
        self.ends, self.solved = ends, []

    def initial_w(self, values):
        return np.array([1.0])  # the fresh start's point

    def solve(self, w, loose=False):
        which = "fresh" if w[0] == 1.0 else "warm"
        self.solved.append(which)
        f, ok = self.ends[which]
        if f is None:
            raise RuntimeError("no arc could be integrated")
        return dict(w=w, f=f, success=ok, status="Solve_Succeeded" if ok else "Stalled", iterations=5, wall_s=1.0)

    def chi2_constant(self):
        return 0.0

    def dof(self):
        return 100

    def prior_sd(self):
        return {}


@pytest.mark.parametrize("ends, solved, kept", [
    # the fresh solve fits (reduced χ² 1): the warm point is not solved
    (dict(fresh=(50.0, True), warm=(40.0, True)), ["fresh"], "fresh"),
    # the fresh solve did not converge, χ² 160 on 100 dof (above its 99.9 % quantile,
    # 149): the warm point too, the better kept
    (dict(fresh=(80.0, False), warm=(79.0, True)), ["fresh", "warm"], "warm"),
    (dict(fresh=(80.0, False), warm=(81.0, True)), ["fresh", "warm"], "fresh"),
    # not converged, but χ² 100 on 100 dof: within the noise, taken as it is
    (dict(fresh=(50.0, False), warm=(40.0, True)), ["fresh"], "fresh"),
    # the fresh solve misfits (reduced χ² 3) or fails: the warm point decides
    (dict(fresh=(150.0, True), warm=(50.0, True)), ["fresh", "warm"], "warm"),
    (dict(fresh=(None, False), warm=(50.0, True)), ["fresh", "warm"], "warm"),
])
def test_after_inserted_slips_the_warm_point_is_solved_only_when_the_fresh_solve_looks_wrong(
        monkeypatch, ends, solved, kept):
    import identify.fitting.start
    from identify.fitting.mode_sequence.decide import after_insertion

    monkeypatch.setattr(identify.fitting.start, "staged_start", lambda prob, values, seed=0: (values, {}))
    prob, restarts = _Stub(ends), []
    sol = after_insertion(prob, np.array([2.0]), {"mu_max": 0.8}, 3, FitOptions(), restarts)
    assert prob.solved == solved
    (rec,) = restarts
    assert rec["kept"] == kept and rec["slips_inserted"] == 3
    # (the iterations of every solve that ran, a failed one none)
    assert sol["f"] == ends[kept][0] and sol["iterations"] == 5 * sum(ends[x][0] is not None for x in solved)
    assert (rec["warm_half_chi2"] is None) == (solved == ["fresh"])
