"""Slips the event detection missed are found by the fitted model and inserted."""

import dataclasses
import warnings

import numpy as np
import pytest

from identify import FitOptions, SimulationOptions, fit, simulate
from identify.events import extract_events
from identify.params import parameter_set

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
    # with the slip back, the estimates are those of the intact data (well inside 1 σ)
    ref = _fit(events)
    for n in ("mu_max", "mu_min", "tau", "A"):
        assert abs(res[n].value - ref[n].value) < 0.5 * ref[n].stderr, n


def test_nothing_inserted_when_nothing_was_missed(events):
    res = _fit(events)
    assert res.solver["slips_inserted"] == 0
    assert "0 missed slip(s) inserted" in res.report()
