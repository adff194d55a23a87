"""Per-run and per-device candidates in the diagnosis: honest about what one spring cannot
tell, and naming a drift of each run's own on data that have one."""

from types import SimpleNamespace

import numpy as np
import pytest

import identify
from identify.diagnosis.features import FeatureValues
from identify.diagnosis.records import CandidateResult
from identify.diagnosis.rounds import DiagnosisOptions, diagnose
from identify.diagnosis.selection import SIGNATURE_P, _unsigned
from identify.diagnosis.where import _time_by_run_misfits, _time_misfits, run_trends
from identify.model.effects import get_effect
from identify.model.scopes import device_label
from identify.simulation.withheld import QUICK_CONDITIONS, run_name, withheld_dataset

BASE = identify.FitOptions(fixed={"v_stick": 1e-5})


def test_a_spring_factor_per_device_on_one_spring_is_reported_confounded_never_named():
    conds = [c for c in QUICK_CONDITIONS if c[0] == 2.13][:3]
    res = diagnose(withheld_dataset(None, conditions=conds), fit_options=BASE,
                   options=DiagnosisOptions(workers=1, effects=["spring_constant_per_device"]))
    assert res.effects == []
    group = next(g for g in res.confounded if g["effects"] == ["spring_constant_per_device"])
    assert "one device only (k2.13)" in group["why"]
    assert set(group["confounded_with"]) == {"mu_max", "mu_min", "A"}
    rec = next(c for c in res.candidates if c["effect"] == "spring_constant_per_device")
    assert rec["status"] == "not applicable" and rec["note"].startswith("confounded: one device only")
    assert "spring_constant_per_device: one device only" in res.report()
    # nothing that was not refitted is counted as a refit that did not converge
    assert res.not_converged() == []


@pytest.mark.slow
def test_a_drift_of_each_runs_own_rate_and_sign_is_named_with_its_rates():
    """The quick withheld conditions (8 runs, two springs), each run drifting at its own
    rate, 25-75 nm/s with signs alternating. Measured (2026-11-28): named in round 1,
    held-out gap 174 -> 19 nm against a 21 nm noise floor, 7 of 8 rates within their 95 %
    interval (the eighth 2.5 σ off). At least 7 of 8 are asked: with intervals that hold at
    95 % each, two misses or more have a probability of 6 %."""
    traces = withheld_dataset("drift_per_run", conditions=QUICK_CONDITIONS)
    res = diagnose(traces, fit_options=BASE, options=DiagnosisOptions(workers=2, effects=["drift", "drift_per_run"]))
    assert res.effects == ["drift_per_run"]
    assert res.verdict == "adequate"
    names = [run_name(c) for c in QUICK_CONDITIONS]
    truth = get_effect("drift_per_run").run_values(
        list(zip(names, [device_label(None, c[0]) for c in QUICK_CONDITIONS])))
    c = next(c for c in res.candidates if c["effect"] == "drift_per_run")
    assert c["heldout_gap_after_um"] < 0.5 * c["heldout_gap_before_um"]
    held = 0
    for name, t in zip(names, truth):
        lo, hi = c["estimates"][f"drift_rate@run:{name}"]["ci95"]
        held += lo <= t["drift_rate"] <= hi
    assert held >= 7


@pytest.mark.slow
@pytest.mark.parametrize("eid, base, magnitude", [("spring_constant_per_device", "k_scale", 1.15),
                                                  ("load_offset_per_device", "load_offset", None)])
def test_one_devices_own_departure_is_named_per_device_with_its_value(eid, base, magnitude):
    """The quick withheld conditions, one device (k20.3, three of the eight runs) off: its
    spring 15 % stiff, or an extra normal load of its own at the library's realistic
    magnitude; the global candidate beside it. The per-device one is named, over its
    global twin where it has one, its value's 95 % interval holding the truth, and the
    other device's (where it is free) its null."""
    traces = withheld_dataset(eid, magnitude, conditions=QUICK_CONDITIONS)
    glob = get_effect(eid).global_twin or get_effect(eid).__class__.__mro__[1].id
    res = diagnose(traces, fit_options=BASE, options=DiagnosisOptions(workers=2, effects=[glob, eid]))
    assert res.effects == [eid]
    c = next(c for c in res.candidates if c["effect"] == eid and c.get("named"))
    name, value, _ = get_effect(eid).magnitude
    truth = float(value if magnitude is None else magnitude)
    lo, hi = c["estimates"][f"{base}@device:k20.3"]["ci95"]
    assert lo <= truth <= hi, (lo, truth, hi)
    other = c["estimates"].get(f"{base}@device:k2.13")
    if other is not None:
        assert other["ci95"][0] <= get_effect(eid).null[base] <= other["ci95"][1], other


@pytest.mark.slow
def test_a_drift_with_a_wandering_zero_is_named_as_one_with_rates_whose_intervals_hold():
    """The same runs, each with its own rate and a random walk of the camera's zero besides
    (20 nm/√s). Without the walk the rates' intervals held 2 of 8 truths (measured on the
    confusion row, 2026-11-28); a fit with the walk at its true intensity held 8 of 8
    (|z| < 1.7). The diagnosis names the walk over the plain per-run drift by their own
    likelihood ratio, with its intensity chosen by the evidence. Measured (2026-11-29):
    passed, 79 minutes beside CI on 2 cores."""
    traces = withheld_dataset("drift_walk", conditions=QUICK_CONDITIONS)
    res = diagnose(traces, fit_options=BASE,
                   options=DiagnosisOptions(workers=2, effects=["drift_per_run", "drift_walk"]))
    assert res.effects == ["drift_walk"]
    names = [run_name(c) for c in QUICK_CONDITIONS]
    truth = get_effect("drift_walk").run_values(
        list(zip(names, [device_label(None, c[0]) for c in QUICK_CONDITIONS])))
    c = next(c for c in res.candidates if c["effect"] == "drift_walk")
    held = 0
    for name, t in zip(names, truth):
        lo, hi = c["estimates"][f"drift_rate@run:{name}"]["ci95"]
        held += lo <= t["drift_rate"] <= hi
    assert held >= 7
    plain = next(c for c in res.candidates if c["effect"] == "drift_per_run")
    assert plain["note"].startswith("not named:")


def test_each_runs_own_trend_in_time_is_seen_where_the_pooled_one_cancels():
    """Two runs trending in time at equal and opposite rates: the pooled trend sees nothing,
    the runs' own trends see both; white plateau residuals give χ² near its df."""
    rng = np.random.default_rng(0)
    n = 40
    t = np.tile(np.linspace(0.0, 10.0, n), 2)
    run = np.repeat([0, 1], n)
    prob = SimpleNamespace(pl_mean_t=t, runs=[SimpleNamespace(name="a"), SimpleNamespace(name="b")])
    trend = np.where(run == 0, 1.0, -1.0) * (t - 5.0) * 0.4  # ±2 σ over the run
    z = rng.normal(size=2 * n)
    pl = FeatureValues("post_slip_level", trend + z, np.ones(2 * n), run)
    assert _time_misfits(prob, pl)[0].p_value > 0.05  # the pooled trend cancels
    by_run = _time_by_run_misfits(prob, pl)[0]
    assert by_run.p_value < 1e-6 and by_run.feature == "time_by_run"
    ts, idx = run_trends(prob, pl)
    assert list(idx) == [0, 1] and ts[0] > 5 and ts[1] < -5
    white = run_trends(prob, FeatureValues("post_slip_level", z, np.ones(2 * n), run))[0]
    assert float(white @ white) < 9.2  # χ²(2) below its 99 % point


def test_a_drift_per_run_without_its_signature_is_not_named():
    c = CandidateResult(effect="drift_per_run", ok=True, significant=True)
    flat = CandidateResult(effect=None, time_by_run=dict(chi2=7.0, df=8, p=0.54))
    trending = CandidateResult(effect=None, time_by_run=dict(chi2=400.0, df=8, p=1e-80))
    assert "do not trend in time within runs" in _unsigned(c, flat)
    assert _unsigned(c, trending) is None
    assert _unsigned(c, CandidateResult(effect=None)) is not None  # no run long enough to tell
    # a global candidate is not held to it
    assert _unsigned(CandidateResult(effect="drift", ok=True), flat) is None
    assert 0 < SIGNATURE_P < 0.05


def _twin(effect, chi2, n_eff, nulls):
    """A significant, converged candidate closing the gap, its residual change the same
    as its twin's (they tie as a confounded group unless told apart)."""
    return CandidateResult(effect=effect, ok=True, significant=True, status="Solve_Succeeded", chi2=chi2,
                           n_eff=n_eff, delta_aic=-400.0 + 2 * n_eff, dr=np.ones(5), closes=True,
                           nulls=nulls, estimates={n: dict(value=2e-6, stderr=1e-7) for n in nulls},
                           estimate_text="offset", gap=dict(noise_um=0.02))


@pytest.mark.parametrize("per_device_gain, named", [(3.0, "load_offset"), (40.0, "load_offset_per_device")])
def test_a_global_candidate_and_its_per_device_twin_are_told_apart_by_their_own_ratio(per_device_gain, named):
    """Two devices: the per-device offset has one more value than the global one. Its
    values agree within noise (Δχ² 3 for one more: p = 0.08) → the global one is named;
    apart (Δχ² 40, p = 3e-10, ΔBIC below 0 at 5000 rows) → the per-device one."""
    from identify.diagnosis.selection import nested_twins, select_named

    base = CandidateResult(effect=None, chi2=5400.0, n_obs=5000, n_eff=4)
    g = _twin("load_offset", 5000.0, 5, {"load_offset": 0.0})
    s = _twin("load_offset_per_device", 5000.0 - per_device_gain, 6,
              {"load_offset@device:k2.13": 0.0, "load_offset@device:k20.3": 0.0})
    assert get_effect("load_offset_per_device").global_twin == "load_offset"
    assert get_effect("spring_constant_per_device").global_twin is None  # its reference: not nested
    kept, out = nested_twins([g, s], base)
    assert [c.effect for c in kept] == [named] and len(out) == 1
    assert out[0].note.startswith("not named:") and "degrees of freedom" in out[0].note
    chosen, group, scored = select_named([g, s], base)
    assert group is None and chosen is not None and chosen.effect == named
    left = next(c for c in scored if c.effect != named)
    assert left.note.startswith("not named:")
    # without the twin rule the two would tie: same residual change, ΔAIC within 10
    from identify.diagnosis.selection import try_named

    assert try_named(g, [s])[1] is not None


def test_a_larger_twin_whose_refit_did_not_converge_leaves_the_name_to_the_converged_one():
    """The walk (drift per run plus a random walk) fits far better than the drift per run
    but its refit ended at the iteration limit: the twin test needs both at their optimum,
    and the converged drift per run stays nameable."""
    from identify.diagnosis.selection import nested_twins, select_named

    base = CandidateResult(effect=None, chi2=50000.0, n_obs=5000, n_eff=4,
                           time_by_run=dict(chi2=400.0, df=8, p=1e-80))  # (the runs trend: a drift may be named)
    g = _twin("drift_per_run", 30000.0, 12, {"drift_rate@run:a": 0.0})
    s = _twin("drift_walk", 21000.0, 48, {"drift_rate@run:a": 0.0, "walk_1@run:a": 0.0})
    s = s.but(status="Maximum_Iterations_Exceeded")
    assert get_effect("drift_walk").global_twin == "drift_per_run"
    kept, out = nested_twins([g, s], base)
    assert [c.effect for c in kept] == ["drift_per_run"]
    assert out[0].effect == "drift_walk" and "did not converge (Maximum_Iterations_Exceeded)" in out[0].note
    chosen, group, _ = select_named([g, s], base)
    assert group is None and chosen is not None and chosen.effect == "drift_per_run"
    # converged, the walk's extra values would win
    kept, _ = nested_twins([g, s.but(status="Solve_Succeeded")], base)
    assert [c.effect for c in kept] == ["drift_walk"]
