"""Fast tests of the paper's smooth route (tests/bench/smooth_baseline.py), the simulator
benchmark's baseline."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

import identify
from identify import Model, ParameterError, SimulationOptions, parameter_set

sys.path.insert(0, str(Path(__file__).parent / "bench"))
from smooth_baseline import (  # noqa: E402
    V_REG,
    SmoothODE,
    SmoothOptions,
    _EpisodeTracker,
    simulate_smooth,
)

K = 2.13  # N/m


def _case(**kw):
    base = dict(
        spring_constant_N_per_m=K, step_frequency_Hz=10.0, normal_load_uN=5.0, travel_um=4.0
    )
    base.update(kw)
    return base


def test_jacobian_matches_finite_differences():
    # every effect switched on, so the hand-written derivatives of each term are checked
    P = {
        **parameter_set(
            "FOTAS",
            {
                "beta": 3e9,
                "topo_amp": 0.02,
                "topo_phase": 0.3,
                "k_scale": 1.1,
                "load_scale": 0.9,
                "load_offset": 1e-7,
                "c_extra": 1e-7,
            },
        ),
        "k": K,
        "Nb": 5e-6,
    }
    ode = SmoothODE(Model(), P, V_REG)
    ode.xp, ode.x_ref = 1.5e-6, 0.2e-6
    for y in ([1e-8, 3e-9, 0.7], [1e-8, -2e-8, 0.6], [0.0, 1e-3, 0.5], [3e-7, -4e-2, 0.55]):
        y = np.array(y)
        J = ode.jac(0.0, y)
        Jn = np.zeros((3, 3))
        for j, floor in enumerate((1e-15, 1e-15, 1e-9)):
            h = max(abs(y[j]) * 1e-6, floor)
            yp, ym = y.copy(), y.copy()
            yp[j] += h
            ym[j] -= h
            Jn[:, j] = (ode.rhs(0.0, yp) - ode.rhs(0.0, ym)) / (2 * h)
        scale = np.abs(J).max(axis=1, keepdims=True)
        assert np.all(np.abs(J - Jn) <= 1e-5 * scale), (y, J, Jn)


@pytest.mark.parametrize("method", ["Radau", "LSODA"])
def test_slips_agree_with_hybrid(method):
    """4 µm at fp = 10 Hz, Nb = 5 µN: three or four slips of ~0.7 µm, each after >= 1.5 s
    of aging (the first after 41 steps).

    The smooth block is never quite at rest: in a stick it creeps at
    v_reg·artanh(F_s/(ψN)) ~ a few v_reg, which rejuvenates ψ by ~ τ·|v|/dc (a few per
    cent below μmax at v_reg = 1e-8 m/s) so it slips at a slightly lower peak and slides
    a little less. Measured: peak −0.06 µm, slip −0.11 µm (DESIGN.md reports ~0.3 µm at
    larger loads, where the same relative bias is more micrometres). The bounds, 0.3 µm
    on the slip and 0.2 µm on the peak, are several times that bias and well below a
    slip (0.78 µm), so a wrong event extraction or wrong physics fails them.
    """
    hyb = identify.simulate("FOTAS", **_case(), options=SimulationOptions(record=False))
    sm = simulate_smooth("FOTAS", **_case(), method=method, max_wall_s=60)
    assert sm.finished
    # shorter slips fit one more into the same travel: counts within one
    assert len(hyb.events) >= 3 and abs(len(sm.events) - len(hyb.events)) <= 1
    h_slip = hyb.events["slip_length_m"].mean()
    s_slip = sm.events["slip_length_m"].mean()
    assert abs(s_slip - h_slip) < 0.3e-6
    assert (
        abs(sm.events["peak_elongation_m"].mean() - hyb.events["peak_elongation_m"].mean()) < 0.2e-6
    )
    # the bias has the sign of the mechanism: the smooth block slips earlier and shorter
    assert s_slip < h_slip
    # a real slip: cm/s peak speed, like the hybrid's (2-3 cm/s, MODEL.md Fig. 13)
    vh, vs = hyb.events["peak_speed_m_per_s"].mean(), sm.events["peak_speed_m_per_s"].mean()
    assert 0.5 * vh < vs < 1.5 * vh
    assert sm.n_rhs > 0 and sm.wall_time_s > 0
    s = sm.summary()
    assert s["n_slips"] == len(sm.events) and s["regime"] == hyb.regime == "stick-slip"


def test_tanh_stick_holds_below_capacity():
    """Nb = 30 µN, 2 µm of travel: the spring force (≤ 4.3 µN) stays far below ψ·N (24 µN).

    The regularised block then only creeps at v ≈ v_reg·artanh(F_s/(μN)) (~0.2 v_reg):
    no slip, speed ~ 0, displacement well under a nanometre per second.
    """
    sm = simulate_smooth(
        "FOTAS",
        **_case(normal_load_uN=30.0, travel_um=2.0, step_frequency_Hz=100.0),
        method="LSODA",
        keep_trajectory=True,
    )
    assert sm.finished and len(sm.events) == 0 and sm.regime == "no-slip"
    tr = sm.trajectory
    assert np.max(np.abs(tr["v"])) < 1e-8  # below v_reg: held
    assert np.max(np.abs(tr["x"])) < 1e-9  # < 1 nm over 0.45 s
    # the creep speed at the end is the tanh's quasi-static one
    P = parameter_set("FOTAS")
    e_end = tr["xp"][-1] - tr["x"][-1]
    ratio = K * e_end / (tr["psi"][-1] * 30e-6)
    assert tr["v"][-1] == pytest.approx(V_REG * math.atanh(ratio), rel=0.05)
    assert tr["psi"][-1] > P["mu_max"] - 0.01  # it ages (almost) as at rest


def test_budget_stops_run_and_marks_it_unfinished():
    sm = simulate_smooth("FOTAS", **_case(travel_um=20.0), method="Radau", max_wall_s=0.2)
    assert not sm.finished
    assert "did not finish" in sm.message
    assert sm.wall_time_s < 2.0
    assert sm.t_reached < sm.conditions.end_time
    assert sm.travel_reached_m < 20e-6
    assert not sm.summary()["finished"]


def test_episode_tracker_extracts_slip_quantities():
    tr = _EpisodeTracker(1e-6)
    t = np.linspace(0.0, 1.0, 11)
    v = np.array([0, 0, 0, 1e-3, 5e-2, 1e-3, 0, 0, 0, 0, 0], float)
    x = np.array([0, 0, 0, 0, 1, 2, 3, 3, 3, 3, 3], float) * 1e-7
    tr.feed(t[:5], x[:5], v[:5], xp=2e-6)  # the episode spans two solver calls
    tr.feed(t[4:], x[4:], v[4:], xp=2e-6)
    ev = tr.finish(True)
    assert len(ev) == 1
    assert ev["slip_length_m"][0] == pytest.approx(3e-7)
    assert ev["peak_elongation_m"][0] == pytest.approx(2e-6)  # xp − x at the last slow point
    assert ev["peak_speed_m_per_s"][0] == pytest.approx(5e-2)
    assert ev["time_s"][0] == pytest.approx(0.2)
    assert ev["duration_s"][0] == pytest.approx(0.4)


def test_options_and_law_are_checked():
    with pytest.raises(ValueError, match="method"):
        SmoothOptions(method="RK45")
    with pytest.raises(ValueError, match="atol"):
        SmoothOptions(atol=(1e-12, 1e-10))
    assert SmoothOptions().detect_speed == pytest.approx(100 * V_REG)
    P = {**parameter_set("FOTAS"), "k": K, "Nb": 5e-6}
    with pytest.raises(ParameterError, match="exponential"):
        SmoothODE(Model("logistic"), P, V_REG)
