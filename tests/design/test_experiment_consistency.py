"""Design's answers agree with each other and say why when they cannot give one
(issue: what users do wrong and expect, item 4)."""

import inspect

from design import Candidate, design_experiment, operating_ranges
from identify.fitting.stick_choice import STICK_SPEED_AUTO


def test_ranges_and_experiment_plan_with_one_stick_option():
    # (ranges kept the equations as written while experiment planned with the stick
    # option: ranges called 5 µN / 100 Hz creep and experiment put it in its plan)
    for fn in (operating_ranges, design_experiment):
        assert inspect.signature(fn).parameters["stick_speed_m_per_s"].default == STICK_SPEED_AUTO
    r = operating_ranges(2.13, loads_uN=[5], fps_Hz=[100], travel_um=100)
    assert r.regimes[0, 0] == "stick-slip"
    assert "stick option 1e-05 m/s" in r.report()


def test_a_reference_that_cannot_be_compared_says_why():
    cands = [Candidate(2.13, nb, fp, 12.0) for nb in (5.0, 10.0) for fp in (30.0, 100.0)]
    plan = design_experiment(2, candidates=cands, travel_um=12.0)
    assert "carry information, too little to fix" in plan.reference_note
    text = plan.report()
    assert "reference / plan = nan" not in text and "cannot be compared" in text
    assert plan.to_json()["reference_plan"]["note"] == plan.reference_note
    assert "(stick option v_stick = 1e-05 m/s)" in text.splitlines()[0]
