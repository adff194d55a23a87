"""The diagnosis on data whose effect the baseline does not have (slow: full diagnoses).

Data: :func:`identify.simulation.withheld.withheld_dataset` — eight of the bundled conditions (the
300 Hz run at 100 Hz, off the stick threshold's knife edge; 8 runs, 90 nm, two frames
per step) with one effect on. The confusion table over every effect and the
detection limits are in ``tests/bench/bench_diagnosis.py``.
"""

import json
from pathlib import Path

import pytest

import identify
from identify.diagnosis.rounds import DiagnosisOptions, diagnose
from identify.jsonio import jsonable as _jsonable
from identify.simulation.withheld import CONDITIONS, withheld_dataset

pytestmark = pytest.mark.slow

DATA = Path(__file__).resolve().parents[3] / "data" / "FOTAS"
BASE = identify.FitOptions(fixed={"v_stick": 1e-5})
NO_A = identify.FitOptions(fixed={"v_stick": 1e-5, "A": 0.0}, free=("mu_max", "mu_min", "tau"))


def _closes(c, share=0.5):
    return c["heldout_gap_after_um"] < c["heldout_gap_before_um"] and c.get("closed_fraction", 0) >= share


def test_the_papers_story_velocity_strengthening():
    """Bundled FOTAS data (A = 0.015), baseline fixing A = 0: slips too long; A closes it."""
    res = diagnose([DATA], fit_options=NO_A, options=DiagnosisOptions(workers=2))
    assert res.effects[:1] == ["velocity_strengthening"]
    c = next(c for c in res.candidates if c["effect"] == "velocity_strengthening")
    assert _closes(c)
    assert c["estimates"]["A"]["value"] == pytest.approx(0.015, rel=0.1)
    assert res.verdict == "adequate"


def test_model_made_data_come_out_adequate():
    res = diagnose([DATA], fit_options=BASE, options=DiagnosisOptions(workers=2))
    assert res.verdict == "adequate" and res.effects == []


def test_an_effect_outside_the_library_is_unexplained():
    traces = withheld_dataset("outside", conditions=CONDITIONS)
    res = diagnose(traces, fit_options=BASE, options=DiagnosisOptions(workers=2))
    assert res.verdict == "unexplained"


@pytest.mark.parametrize("eid", ["drift",  # named with the 300 Hz run at 100 Hz (withheld.CONDITIONS)
                                 "step_size",
                                 "load_offset",
                                 "spring_nonlinearity",
                                 "topography",  # its refit from every leading ripple (50fbad5)
                                 # its mode sequence decided from the detected one too (84fb0c6):
                                 # named, `adequate`, held-out gap 0.162 -> 0.025 µm; ~22 min
                                 "aging_logarithmic",
                                 # absorbed by the friction coefficients (μ·Nb/k sets every elongation)
                                 "spring_constant", "load_scale",
                                 # v_stick 1e-4 against the baseline's 1e-5: mimicked by μmax, μmin, τ
                                 "stick_threshold",
                                 # not seen near its null, nor at 2e-5 N s/m: past that much damping a slip
                                 # ends without overshoot, so A absorbs it; confounded at its magnitude (A,
                                 # μmax, μmin 8-9× and τ 3.5× less certain there than the baseline states)
                                 "damping"])
def test_withheld_effect_is_named(eid):
    traces = withheld_dataset(eid, conditions=CONDITIONS, base={"A": 0.015})
    res = diagnose(traces, fit_options=BASE, options=DiagnosisOptions(workers=2))
    c = next(c for c in res.candidates if c["effect"] == eid)
    assert eid in res.effects or c["confounded_with"], res.report()
    if eid in res.effects:
        assert c["heldout_gap_after_um"] < c["heldout_gap_before_um"]
    else:
        assert eid not in res.effects and not c.get("named")


def test_logistic_law_data_point_to_the_logistic_law_confounded_with_tau():
    """The logistic law at Table II (dc = 20 nm): a contact loses its seed in its first
    slip and never re-ages, so no run stick-slips and nothing can be fitted. Honestly
    `unexplained`, nothing named; the regime screen finds the logistic law the only
    candidate that makes such runs, and the exponential law makes them too with τ ≥ 67.4 s
    (1000× the preset): reported as confounded with τ (measured: the current model
    parts from 6 of 8 runs, χ² 1737; the logistic law from none, its largest slips
    agreeing, slip χ² 0.63; the others 2-7; no other own parameter moved alone makes them —
    μmax ≤ 0.5 keeps their regime but loses their first slip; 20 s)."""
    traces = withheld_dataset("aging_logistic", conditions=CONDITIONS, base={"A": 0.015})
    res = diagnose(traces, fit_options=BASE, options=DiagnosisOptions(workers=2))
    assert res.verdict == "unexplained" and res.effects == [] and res.baseline is None
    current, *screen = res.regime_screen
    assert current["effect"] is None and current["mismatched"] >= 4
    assert [r["effect"] for r in screen if r["reproduces_regime"]] == ["aging_logistic"], res.report()
    assert screen[0]["confounded_with"] == ["tau"], res.report()
    assert [g["effects"] for g in res.confounded] == [["aging_logistic"]]
    assert "aging_logistic reproduces them" in res.notes[-1] and "Confounded with tau, not named" in res.notes[-1]


def test_an_effect_the_data_cannot_see_is_said_so():
    """Motion blur of a 2 ms exposure with two frames per step centred in the half-step
    intervals: no frame's exposure reaches a step and slip frames are left out, so nothing
    in the data shows it. Honestly: not named, and at its realistic magnitude it fits as
    well with no parameter moved or unpinned (no partner to name)."""
    traces = withheld_dataset("motion_blur", conditions=CONDITIONS, base={"A": 0.015})
    res = diagnose(traces, fit_options=BASE, options=DiagnosisOptions(workers=2))
    c = next(c for c in res.candidates if c["effect"] == "motion_blur")
    assert res.effects == [] and res.verdict == "adequate", res.report()
    assert c["at_magnitude"]["absorbed"] is True and c["at_magnitude"]["partners"] == [], c["note"]
    assert "the data do not see it there" in c["note"]


def test_two_withheld_effects_are_both_named():
    """Forward selection with two effects at once (issue 5, item 3): a load offset and a
    puller step off its metadata, each at its realistic magnitude. Measured at 5373b08: both
    named (load offset in round 1, held-out gap 180 -> 60 nm; step size in round 2, -> 35
    nm), then rejuvenation as a third, undetermined (dc 7.1 ± 8.0 nm, null 20 nm), which its
    own interval now keeps out: at ca2ec0c exactly the two, `adequate`, load offset 1.990 µN
    and step 1.0497, held-out gap 180 -> 35 nm (noise 21 nm); 2488 s beside other jobs."""
    traces = withheld_dataset(["load_offset", "step_size"], conditions=CONDITIONS, base={"A": 0.015})
    res = diagnose(traces, fit_options=BASE, options=DiagnosisOptions(workers=2))
    assert sorted(res.effects) == ["load_offset", "step_size"], res.report()
    assert res.verdict == "adequate", res.report()
    # measured: 2.007e-6 (stderr 3e-8 when named) and 1.0498 (stderr 0.0008); within ~3 and ~4 of them
    assert res.final["values"]["load_offset"] == pytest.approx(2e-6, rel=0.05)
    assert res.final["values"]["step_scale"] == pytest.approx(1.05, abs=0.003)
    first = next(c for c in res.candidates if c["effect"] == res.effects[0])
    assert res.final["heldout_gap_um"] < first["heldout_gap_before_um"]


def test_rejuvenation_is_named_where_the_runs_keep_their_slips():
    """A memory length dc = 0.1 µm against the baseline's 20 nm (0.1× the library's
    departure; at 1 µm six of the eight runs lose their resolvable slips and the verdict
    is honestly `unexplained`, below). Measured at d6b7ba1: named once its refit, past the naming
    screen, may take more rounds (converged in its fifth), dc = 74 ± 11 nm, held-out gap
    22.0 -> 16.5 nm (noise 17.8), `adequate`, 183 s with two workers."""
    traces = withheld_dataset("rejuvenation", 1e-7, conditions=CONDITIONS, base={"A": 0.015})
    res = diagnose(traces, fit_options=BASE, options=DiagnosisOptions(workers=2))
    assert res.effects == ["rejuvenation"] and res.verdict == "adequate", res.report()
    c = next(c for c in res.candidates if c["effect"] == "rejuvenation")
    assert c["heldout_gap_after_um"] < c["heldout_gap_before_um"]
    # measured 74 ± 11 nm: the truth within three standard errors, and far from the null
    est = c["estimates"]["dc"]
    assert abs(est["value"] - 1e-7) < 3 * est["stderr"] and est["ci95"][0] > 2e-8


def test_rejuvenation_at_its_magnitude_is_named_by_the_runs_left_out():
    """dc = 1 µm: six of eight runs creep or step, the two left stick-slip and fit at the
    noise with dc at 20 nm or at 1 µm alike, so no refit of them names it; the six part
    from the final model (3 of 6, χ² 54.3). The screen at the final values points to
    rejuvenation alone; held at 1 µm and refitted it fits the two as well and makes the
    six as the data's; its profile on every run names it: dc's 95 % interval between
    562 nm and 1.78 µm, joint χ² 2799 -> 2745, no own move making every run, the six's
    largest-slip gap 231 nm -> 0 held out (measured at 2b14f43: `adequate`, 364 s beside
    another slow test on two cores)."""
    traces = withheld_dataset("rejuvenation", conditions=CONDITIONS, base={"A": 0.015})
    res = diagnose(traces, fit_options=BASE, options=DiagnosisOptions(workers=2))
    current, *screen = res.regime_screen
    assert current["effect"] is None and current["mismatched"] >= 2
    assert [r["effect"] for r in screen if r["reproduces_regime"]] == ["rejuvenation"], res.report()
    held = next(c for c in res.rounds[-1] if c.get("effect") == "rejuvenation")["held_regime"]
    assert held["fits"] and held["reproduces"] and held["p_value"] < 1e-6, res.report()
    prof = res.regime_profile
    assert prof["named"] and res.effects == ["rejuvenation"] and res.verdict == "adequate", res.report()
    lo, hi = prof["interval"]
    assert lo is not None and hi is not None and lo < 1e-6 < hi and hi / lo < 10  # (truth 1 µm)
    assert prof["slip_gap_heldout_um"] < prof["slip_gap_before_um"]
    assert res.where_final[0].feature != "regime" or res.where_final[0].p_value > 0.01
    assert json.loads(json.dumps(_jsonable(res.to_json())))["regime_profile"]["named"]
    assert "the runs left out for their regime, largest slips" in res.report()
