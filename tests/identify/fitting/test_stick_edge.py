"""The stick threshold's knife edge: runs pulled faster than v_stick are flagged."""

import pytest

from identify.fitting.rundata import RunData


def _run(fp, kind="events"):
    return RunData(name="r", kind=kind, k=2.13, Nb=20e-6, fp=fp, step_nominal=46e-9, sigma=90e-9, n_frames=100)


def test_a_run_pulled_faster_than_the_threshold_is_flagged_with_both_speeds():
    why = _run(300.0).stick_edge({"v_stick": 1e-5})
    assert why is not None and "13.8 µm/s" in why and "v_stick = 10 µm/s" in why


@pytest.mark.parametrize("fp, values, kind", [
    (100.0, {"v_stick": 1e-5}, "events"),                    # 4.6 µm/s: every slip ends
    (300.0, {"v_stick": 0.0}, "events"),                     # the equations as written
    (300.0, {"v_stick": 1e-5, "step_scale": 0.5}, "events"),  # the true step is half: 6.9 µm/s
    (300.0, {"v_stick": 1e-5}, "creep"),                     # no slips to end
])
def test_other_runs_are_not_flagged(fp, values, kind):
    assert _run(fp, kind).stick_edge(values) is None
